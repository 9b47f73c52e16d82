"""The look-alike towers' report: does the motion tell what the look cannot?

`ppdjax.reproduce video` with a preset whose `test.appearance` is set (configs/video.py
`:lookalike`) also trains a model that reads no trajectory on the same data and
decomposes the test towers with it from appearance alone (the network's densities on
the fitted boxes). This module adds to the video report its rows, "which is heavier"
between blocks that look alike, the figure of two towers that look alike and move
otherwise, and the flat keys of RESULTS/{name}.json that the look-alike study is read by.
"""

from __future__ import annotations

import numpy as np

from ppdjax.conventions import density_to_slot
from ppdjax.dataset import materials
from ppdjax.reproduce import video_report as report

TARGETS = {"rmse_all": 5.0, "rmse_2": 3.0, "appearance_ratio": 2.0, "heavier_right": 95.0,
           "pearson_r": 0.95, "tracked": 158, "median_mm": 1.5, "median_deg": 0.2}


def alike_pairs(test: dict, look: str) -> np.ndarray:
  """The 2-block towers whose two blocks look the same (`materials.look_ids`)."""
  shown = materials.look_ids(test["materials"], look)
  two = np.flatnonzero(test["valid"].sum(-1) == 2)
  return two[shown[two, 0] == shown[two, 1]]


def appearance_rows(test: dict, ev: dict, pairs: np.ndarray) -> tuple[dict, dict]:
  """The appearance-only model's density row and its "which is heavier" on `pairs`."""
  blocks = test["valid"].sum(-1)
  ok = np.flatnonzero(ev["true_valid"].any(-1))  # it reads no trajectory: every tower
  row, mass = report.summary(test, ev, "true", ok, blocks)
  with np.errstate(invalid="ignore", divide="ignore"):  # one ratio for all: r is NaN
    return row, report.heavier(test, mass, pairs)


def flat_keys(result: dict, appearance: dict) -> dict:
  """The look-alike study's keys: the tracked headline row, the appearance-only RMSE,
  "which is heavier" between look-alike blocks, the tracking."""
  row, heavy, t = result["density"]["tracked"], result["heavier_alike"], result["tracking"]
  return {"rmse_all": row["rmse_all"], "rmse_all_ci95": row.get("rmse_all_ci95"),
          "rmse_2": row.get("rmse_2_blocks"), "rmse_2_ci95": row.get("rmse_2_blocks_ci95"),
          "appearance_only_rmse": appearance["rmse_all"],
          "appearance_only_rmse_ci95": appearance.get("rmse_all_ci95"),
          "heavier_right": heavy["heavier_right_percent"], "pearson_r": heavy["pearson_log2"],
          "heavier_towers": heavy["towers"], "tracked": t["tracked"], "towers": t["clips"],
          "median_mm": t["position_mm_median"], "median_deg": t["rotation_deg_median"],
          "targets": TARGETS}


def twin_towers(test: dict, pairs: np.ndarray, min_log2_apart: float = 2.0):
  """Two of `pairs` (2-block towers of one look) most alike in shape whose upper / lower
  mass ratios differ by at least 2^min_log2_apart: (i, j), or None."""
  if len(pairs) < 2:
    return None
  mass = test["density"] * 8 * np.prod(test["half_size"], -1)
  order = np.argsort(np.where(test["valid"], test["pos"][..., 2], np.inf), -1)[:, :2]
  take = lambda a: np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 2)),
                                      1)  # noqa: E731
  shape = np.concatenate([take(test["half_size"]).reshape(len(mass), -1),
                          take(test["pos"]).reshape(len(mass), -1)], -1)[pairs]
  ratio = np.log2(take(mass)[:, 1] / take(mass)[:, 0])[pairs]
  apart = np.abs(ratio[:, None] - ratio[None]) >= min_log2_apart
  dist = np.where(apart, np.linalg.norm(shape[:, None] - shape[None], axis=-1), np.inf)
  if not np.isfinite(dist).any():
    return None
  a, b = np.unravel_index(np.argmin(dist), dist.shape)
  return int(pairs[a]), int(pairs[b])


def plot_twins(test: dict, full: dict, appearance: dict, twins, path: str) -> None:
  """Two towers that look alike, their tracked motion, and the densities each model reads
  (slots, bottom block first)."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  full_d, _ = report.matched(test, full, "tracked")
  app_d, _ = report.matched(test, appearance, "true")
  fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
  for ax, i in zip(axes[:2], twins):
    valid = test["valid"][i]
    order = np.argsort(np.where(valid, test["pos"][i, :, 2], np.inf))[:valid.sum()]
    slots = lambda dens, order=order: density_to_slot(np.nan_to_num(dens[order], nan=100.0))
    ax.imshow(test["image"][i])
    ax.set_title(f"tower {i}: truth {slots(test['density'][i]).tolist()}\n"
                 f"motion + look {slots(full_d[i]).tolist()}, look alone "
                 f"{slots(app_d[i]).tolist()}", fontsize=8)
    ax.axis("off")
  for i, style in zip(twins, ("-", "--")):
    traj = test["tracked_trajectory"][i]
    if np.isfinite(traj).all():
      axes[2].plot(np.linalg.norm(traj[:, :3] - traj[:1, :3], axis=-1), style,
                   label=f"tower {i}")
  axes[2].set(xlabel="step", ylabel="displacement (m), tracked",
              title="the same look, struck alike")
  axes[2].legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def report_md(keys: dict, appearance: dict, heavy_app: dict, figure: str | None) -> str:
  """The look-alike section of the report (appended to the video report's)."""
  met = lambda ok: "yes" if ok else "**no**"  # noqa: E731
  t = TARGETS
  ratio = keys["appearance_only_rmse"] / max(keys["rmse_all"], 1e-9)
  lines = [
      "", "## Look-alike towers: the motion against the look", "",
      "| target | ours | goal | met |", "|---|--:|--:|:-:|",
      f"| density RMSE, all towers (tracked) | {keys['rmse_all']:.2f} | ≤ {t['rmse_all']:g} | "
      f"{met(keys['rmse_all'] <= t['rmse_all'])} |",
      f"| density RMSE, 2-block towers | {keys['rmse_2'] or float('nan'):.2f} | "
      f"≤ {t['rmse_2']:g} | {met((keys['rmse_2'] or 99) <= t['rmse_2'])} |",
      f"| appearance only / motion RMSE | {ratio:.2f} ({keys['appearance_only_rmse']:.2f}) | "
      f"≥ {t['appearance_ratio']:g} | {met(ratio >= t['appearance_ratio'])} |",
      f"| which is heavier, look-alike blocks (%) | {keys['heavier_right']:.1f} "
      f"({keys['heavier_towers']} towers) | ≥ {t['heavier_right']:g} | "
      f"{met(keys['heavier_right'] >= t['heavier_right'])} |",
      f"| Pearson r, log2 mass ratios | {keys['pearson_r']:.3f} | ≥ {t['pearson_r']:g} | "
      f"{met(keys['pearson_r'] >= t['pearson_r'])} |",
      f"| clips tracked | {keys['tracked']} of {keys['towers']} | ≥ {t['tracked']} | "
      f"{met(keys['tracked'] >= t['tracked'])} |",
      f"| tracking median | {keys['median_mm']:.2f} mm, {keys['median_deg']:.2f}° | "
      f"≤ {t['median_mm']:g} mm, {t['median_deg']:g}° | "
      f"{met(keys['median_mm'] <= t['median_mm'] and keys['median_deg'] <= t['median_deg'])} |",
      "", f"The appearance-only model (the same data, no trajectory; the network's densities "
      f"on the fitted boxes): RMSE {report._ci(appearance, 'rmse_all')} over "
      f"{appearance['towers']} towers, top-1 {appearance['top1_percent']:.1f} %; which is "
      f"heavier between look-alike blocks {heavy_app['heavier_right_percent']:.1f} % "
      f"(Pearson r {heavy_app['pearson_log2']:.3f})."]
  if figure:
    lines += ["", f"![two towers that look alike]({figure})"]
  return "\n".join(lines) + "\n"


def extend_report(pipe, results_dir: str, name: str, result: dict) -> dict:
  """Adds the look-alike rows, keys, section and figure to the video report `name` that
  `video_report.write_report` wrote (its `result`); returns the flat keys."""
  import json  # pylint: disable=import-outside-toplevel
  import os  # pylint: disable=import-outside-toplevel
  test = dict(np.load(pipe.test_file))
  full = dict(np.load(pipe.eval_files["refine" if pipe.config.eval.refine else "sample"]))
  app = dict(np.load(pipe.eval_files["appearance"]))
  pairs = alike_pairs(test, pipe.config.data.get("look", "material"))
  blocks = test["valid"].sum(-1)
  ok = np.flatnonzero(full["tracked_valid"].any(-1))
  _, mass = report.summary(test, full, "tracked", ok, blocks)
  result["heavier_alike"] = report.heavier(test, mass, np.intersect1d(pairs, ok))
  appearance, heavy_app = appearance_rows(test, app, pairs)
  result["density"]["appearance only"] = appearance
  result["heavier"]["appearance only"] = heavy_app
  keys = flat_keys(result, appearance)
  result.update(keys)
  twins = twin_towers(test, np.intersect1d(pairs, ok))
  figure = None
  if twins is not None:
    figure = f"{name}_twins.png"
    plot_twins(test, full, app, twins, os.path.join(results_dir, figure))
    result["twins"] = list(twins)
  with open(os.path.join(results_dir, f"{name}.json"), "w") as f:
    json.dump(result, f, indent=1)
  video_json = os.path.join(results_dir, "video.json")  # its entry, with the keys above
  if os.path.exists(video_json):
    with open(video_json) as f:
      merged = json.load(f)
    merged.setdefault("lookalike_towers", {}).update(keys)
    with open(video_json, "w") as f:
      json.dump(merged, f, indent=1)
  with open(os.path.join(results_dir, f"{name}.md"), "a") as f:
    f.write(report_md(keys, appearance, heavy_app, figure))
  return keys
