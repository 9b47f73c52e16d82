"""The report of ppdjax.reproduce video, from the evaluate step's files (`video_decompose`)."""

from __future__ import annotations

import json
import os

import numpy as np

from ppdjax.report.provenance import write_provenance
from ppdjax.reproduce import steps as pipeline_steps
from ppdjax.conventions import density_to_slot
from ppdjax.metrics import relative_rotation
from ppdjax.dataset import materials
from ppdjax.reproduce.video_decompose import WAYS

VALIDATION_SUFFIX = "_val"  # report NAME's headline was chosen on report NAME_val's towers
SEARCH_STUDY = "video_search"  # where the look-alike preset's +Search settings were chosen
LATER_QUESTION = "starts"  # the section of SEARCH_STUDY's results that chose last


def validation_summary(results_dir: str, name: str):
  """How config.eval.refine was chosen: the validation report's (`name` + "_val") tracked
  RMSE with and without refinement (None for a validation report itself, or before its
  validation report exists)."""
  report = name + VALIDATION_SUFFIX
  path = os.path.join(results_dir, f"{report}.json")
  if name.endswith(VALIDATION_SUFFIX) or not os.path.exists(path):
    return None
  with open(path) as f:
    val = json.load(f)
  d = val["density"]
  pick = lambda key: next(v["rmse_all"] for k, v in d.items() if k == key)  # noqa: E731
  refine_first = val["decompose"]["refine"]
  out = {"report": f"{report}.md", "seed": val["seed"], "density_rmse_tracked": {
      "refine": pick("tracked" if refine_first else "tracked, +Refine"),
      "sample": pick("tracked, +Sample only" if refine_first else "tracked")}}
  search = os.path.join(results_dir, SEARCH_STUDY + ".json")
  if name == "video_lookalike" and os.path.exists(search):  # +Search chosen on its towers
    with open(search) as f:
      study = json.load(f)
    # its later question (refining from several starts, on a model of its own) if asked
    study = study.get(LATER_QUESTION, study)
    rows = study["validation"]["rows"]
    out["search"] = {"study": f"experiments/{SEARCH_STUDY}/README.md", "chosen": study["chosen"],
                     "against": study.get("baseline", "pipeline_refine"),
                     "density_rmse_tracked": {k: v["rmse_all"] for k, v in rows.items()
                                              if not k.endswith("_before_refinement")}}
  return out


PAPER = {"rmse_all": 18.7, "rmse_2_blocks": 10.1, "random": 40.8, "pearson_model_truth": 0.90}
TARGETS = {"rmse_all": 10.0, "rmse_2_blocks": 5.0, "pearson": 0.95}
LOG2_LEVELS = np.arange(-4, 5)  # the paper's answer scale {2^k, k = -4..4}


def nearest_boxes(test: dict, ev: dict, way: str) -> np.ndarray:
  """(B, K) the index of the predicted box nearest each true block's centre."""
  pos, valid = ev[f"{way}_pos"], ev[f"{way}_valid"]
  dist = np.linalg.norm(test["pos"][:, :, None] - pos[:, None], axis=-1)  # (B, K, K')
  dist = np.where(valid[:, None], dist, np.inf)
  return np.argmin(np.nan_to_num(dist, nan=np.inf), -1)


def matched(test: dict, ev: dict, way: str):
  """(B, K) predicted density and mass of the box nearest each true block (NaN: none)."""
  valid, nearest = ev[f"{way}_valid"], nearest_boxes(test, ev, way)
  take = lambda a: np.take_along_axis(a, nearest, 1)  # noqa: E731
  dens = take(ev[f"{way}_density"])
  volume = 8 * np.prod(ev[f"{way}_half_size"], -1)
  ok = test["valid"] & valid.any(-1, keepdims=True)
  return np.where(ok, dens, np.nan), np.where(ok, dens * take(volume), np.nan)


def rmse_slots(pred_density, test, towers_idx) -> float:
  err = (density_to_slot(np.nan_to_num(pred_density[towers_idx], nan=100.0))
         - density_to_slot(test["density"][towers_idx])).astype(float)
  return float(np.sqrt((err[test["valid"][towers_idx]] ** 2).mean()))


def summary(test, ev, way, ok, blocks) -> dict:
  dens, mass = matched(test, ev, way)
  row = {"towers": int(len(ok))}
  for name, sel in (("all", ok), ("2_blocks", ok[blocks[ok] == 2]),
                    ("3_blocks", ok[blocks[ok] == 3]), ("4_blocks", ok[blocks[ok] == 4])):
    if len(sel) == 0:
      continue
    stat = lambda idx, sel=sel: rmse_slots(dens, test, sel[idx])  # noqa: E731
    from ppdjax.metrics import bootstrap_interval  # pylint: disable=import-outside-toplevel
    row[f"rmse_{name}"] = rmse_slots(dens, test, sel)
    row[f"rmse_{name}_ci95"] = bootstrap_interval(stat, len(sel))
    row[f"towers_{name}"] = int(len(sel))
  true_slot = density_to_slot(test["density"])
  pred_slot = density_to_slot(np.nan_to_num(dens, nan=100.0))
  v = test["valid"][ok]
  row["top1_percent"] = float(100 * (pred_slot[ok] == true_slot[ok])[v].mean())
  real = np.array(list(materials.REAL_MATERIALS.values())) - 1
  nearest_material = real[np.argmin(np.abs(pred_slot[..., None] - real), -1)]
  row["material_accuracy_percent"] = float(100 * (nearest_material[ok] == true_slot[ok])[v].mean())
  return row, mass


def heavier(test, mass, two) -> dict:
  """Upper / lower block mass ratios on the 2-block towers, log2, true and the model's."""
  true_mass = test["density"] * 8 * np.prod(test["half_size"], -1)
  upper = np.argmax(np.where(test["valid"], test["pos"][..., 2], -np.inf), -1)
  lower = np.argmin(np.where(test["valid"], test["pos"][..., 2], np.inf), -1)
  pick = lambda a, i: np.take_along_axis(a, i[:, None], 1)[:, 0]  # noqa: E731
  truth = np.log2(pick(true_mass, upper) / pick(true_mass, lower))[two]
  model = np.log2(pick(mass, upper) / pick(mass, lower))[two]
  ok = np.isfinite(model)
  q = lambda x: np.clip(np.rint(x), LOG2_LEVELS[0], LOG2_LEVELS[-1])  # noqa: E731
  return {"towers": int(ok.sum()), "true_log2": truth.tolist(), "model_log2": model.tolist(),
          "pearson_levels": float(np.corrcoef(q(truth[ok]), q(model[ok]))[0, 1]),
          "pearson_log2": float(np.corrcoef(truth[ok], model[ok])[0, 1]),
          "same_level_percent": float(100 * (q(truth[ok]) == q(model[ok])).mean()),
          "heavier_right_percent": float(100 * (np.sign(truth[ok]) == np.sign(model[ok])).mean())}


def random_guess_rmse(test) -> dict:
  """RMSE (slots) of guessing uniformly among the four real materials, and among all 100
  slots, in expectation over the guesses."""
  true_slot = density_to_slot(test["density"])[test["valid"]].astype(float)
  real = np.array(list(materials.REAL_MATERIALS.values()), float) - 1
  four = float(np.sqrt(((true_slot[:, None] - real) ** 2).mean()))
  every = float(np.sqrt(((true_slot[:, None] - np.arange(100)) ** 2).mean()))
  return {"four_materials": four, "hundred_slots": every}


def tracking_errors(test) -> dict:
  tr, tt = test["tracked_trajectory"], test["true_trajectory"]
  ok = np.isfinite(tr).all((1, 2))
  pos = 1e3 * np.linalg.norm(tr[ok, :, :3] - tt[ok, :, :3], axis=-1)
  rot = np.degrees(np.linalg.norm(relative_rotation(tr[ok, :, 3:], tt[ok, :, 3:]), axis=-1))
  return {"clips": int(len(ok)), "tracked": int(ok.sum()),
          "position_mm_median": float(np.median(np.median(pos, 1))),
          "position_mm_p90_of_clip_medians": float(np.percentile(np.median(pos, 1), 90)),
          "rotation_deg_median": float(np.median(np.median(rot, 1))),
          "failures": [str(e) for e in test["errors"] if e]}


def plot_heavier(h: dict, path: str) -> None:
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  truth = np.asarray(h["tracked"]["true_log2"])
  order = np.argsort(truth)
  fig, ax = plt.subplots(figsize=(10, 3.6))
  x = np.arange(len(truth))
  ax.plot(x, truth[order], "k-", lw=2, label="truth")
  for way, style in (("tracked", "o"), ("true", "x")):
    ax.plot(x, np.asarray(h[way]["model_log2"])[order], style, ms=4,
            label=f"model, {way} trajectory (r = {h[way]['pearson_log2']:.2f})")
  ax.set_yticks(LOG2_LEVELS, [f"$2^{{{k}}}$" for k in LOG2_LEVELS])
  ax.set_ylim(-7.5, 7.5)
  ax.set_xlabel("2-block test towers, by true ratio")
  ax.set_ylabel("mass of upper / lower block")
  ax.set_title('Which block is heavier (paper Fig. 9): model vs truth')
  ax.grid(alpha=0.3)
  ax.legend(fontsize=8, loc="upper left")
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def write_report(pipe, results_dir: str, command: str, name: str = "video_towers") -> dict:
  """Writes RESULTS/{name}.md and .json, the figure, and the summary into video.json (key
  "real_towers" for video_towers, "lookalike_towers" for video_lookalike, their
  validation reports' (NAME_val) "real_towers_validation" / "lookalike_towers_validation",
  any other name its own)."""
  test = dict(np.load(pipe.test_file))
  blocks = test["valid"].sum(-1)
  two = np.flatnonzero(blocks == 2)
  headline = "refine" if pipe.config.eval.refine else "sample"
  rows, heavy = {}, {}
  for variant in (headline,) + tuple(v for v in ("sample", "refine") if v != headline):
    ev = dict(np.load(pipe.eval_files[variant]))
    tag = "" if variant == headline else (", +Refine" if variant == "refine"
                                         else ", +Sample only")
    for way in WAYS:
      ok = np.flatnonzero(ev[f"{way}_valid"].any(-1))
      rows[way + tag], mass = summary(test, ev, way, ok, blocks)
      heavy[way + tag] = heavier(test, mass, two)
    if not tag:  # like for like: the tracker's cost on the towers it tracked
      tracked_ok = np.flatnonzero(ev["tracked_valid"].any(-1))
      rows["true, tracked towers only"] = summary(test, ev, "true", tracked_ok, blocks)[0]
  result = {"command": command, "config": pipe.config.name, "seed": int(pipe.config.test.seed),
            "towers": int(len(blocks)), "blocks": {str(b): int((blocks == b).sum())
                                                   for b in (2, 3, 4)},
            "video": {"fps": float(pipe.config.test.fps), "frame": list(pipe.config.test.frame),
                      "noise": float(pipe.config.test.noise),
                      "lighting": float(pipe.config.test.lighting),
                      "stickers": str(pipe.config.test.stickers),
                      "fovy": float(pipe.config.test.fovy)},
            "tracking": tracking_errors(test), "density": rows, "heavier": heavy,
            "random_guess_rmse": random_guess_rmse(test), "paper": PAPER, "targets": TARGETS,
            "decompose": {"samples": int(pipe.config.eval.samples),
                          "rounds": int(pipe.config.eval.get("rounds", 1)),
                          "sample_inertia": bool(pipe.config.eval.get("sample_inertia", False)),
                          "search_continuation": int(pipe.config.eval.get("search_continuation",
                                                                          0)),
                          "refine_starts": int(pipe.config.eval.get("refine_starts", 1)),
                          "refine": bool(pipe.config.eval.refine), "fit": True, "depth": True},
            "validation": validation_summary(results_dir, name),
            "steps": pipeline_steps.read_log(pipe.root)}
  os.makedirs(results_dir, exist_ok=True)
  with open(os.path.join(results_dir, f"{name}.json"), "w") as f:
    json.dump(result, f, indent=1)
  write_provenance(os.path.join(results_dir, f"{name}.json"), command=command,
                   config=pipe.config, headlines={
                       f"density RMSE (slots), all towers, {way} trajectory":
                       f"density/{way}/rmse_all" for way in WAYS})
  key = {"video_towers": "real_towers", "video_lookalike": "lookalike_towers"}.get(
      name, ("lookalike_towers_validation" if "lookalike" in name else "real_towers_validation")
      if name.endswith(VALIDATION_SUFFIX) else name)
  figure = "video_heavier.png" if name == "video_towers" else f"{name}_heavier.png"
  video_json = os.path.join(results_dir, "video.json")  # the results file
  merged = json.load(open(video_json)) if os.path.exists(video_json) else {}
  merged[key] = {k: result[k] for k in ("command", "seed", "towers", "blocks", "video",
                                         "tracking", "density", "random_guess_rmse", "paper")}
  merged[key]["heavier"] = {w: {k: v for k, v in h.items() if "log2" != k[-4:]}
                            for w, h in heavy.items()}
  with open(video_json, "w") as f:
    json.dump(merged, f, indent=1)
  plot_heavier({w: heavy[w] for w in WAYS}, os.path.join(results_dir, figure))
  with open(os.path.join(results_dir, f"{name}.md"), "w") as f:
    f.write(report_md(result, figure))
  print(report_md(result, figure))
  return result


def _ci(row, key):
  if key not in row:
    return "–"
  lo, hi = row[f"{key}_ci95"]
  return f"{row[key]:.1f} [{lo:.1f}, {hi:.1f}]"


def _selection_words(d: dict) -> str:
  """How the report's decompositions chose densities (+Sample, or +Search's rounds)."""
  if d.get("rounds", 1) <= 1 and not d.get("sample_inertia"):
    return f"{d['samples']} density samples"
  return (f"+Search ({d.get('rounds', 1)} rounds of {d['samples']} candidates, each later "
          "round near the closest so far" + (", their boxes carrying inertia scales"
                                             if d.get("sample_inertia") else "")
          + (f", round r's closest over the first {d['search_continuation']} x 2^r steps"
             if d.get("search_continuation") else "")
          + "; its winner before refinement is the '+Sample only' rows)")


def _refine_words(d: dict) -> str:
  starts = d.get("refine_starts", 1) if d["refine"] else 1
  if starts > 1:
    return (f"the {starts} closest distinct candidates by trajectory each refined by "
            "Levenberg-Marquardt, the closest refined kept")
  return "the closest by trajectory" + (" refined by Levenberg-Marquardt" if d["refine"] else "")


def _search_words(search: dict | None) -> str:
  if not search:
    return ""
  rmse, against = search["density_rmse_tracked"], search.get("against", "pipeline_refine")
  return (f", and +Search's on the same towers ({search['study']}: refined RMSE "
          f"{rmse[search['chosen']]:.1f} for the chosen {search['chosen']} against "
          + (f"the pipeline's {rmse['pipeline_refine']:.1f})" if against == "pipeline_refine"
             else f"{rmse[against]:.1f} for {against})"))


def report_md(r: dict, figure: str = "video_heavier.png") -> str:
  d, h, t = r["density"], r["heavier"], r["tracking"]
  rg = r["random_guess_rmse"]
  met = lambda ok: "yes" if ok else "**no**"  # noqa: E731
  tracked = d["tracked"]
  lines = [
      "# The paper's real towers, rebuilt in simulation (issue 19; paper Sec. 5.3, 6)", "",
      f"`{r['command']}`", "",
      f"{r['towers']} test towers of seed {r['seed']} (2 / 3 / 4 blocks: "
      f"{r['blocks']['2']} / {r['blocks']['3']} / {r['blocks']['4']}), blocks of pine, "
      "aluminium, steel and copper, each struck once by the copper ball of the pendulum "
      "(`ppdjax.sim.pushes.pendulum_strike`). The model reads the voxels, the image and one "
      f"trajectory, which comes from a video ({r['video']['frame'][1]} x "
      f"{r['video']['frame'][0]} at {r['video']['fps']:g} fps, motion blur, noise "
      f"{r['video']['noise']:g} grey levels, lighting drift ±{100 * r['video']['lighting']:.0f} %) "
      "through the sticker tracker; beside it, the same model fed the true trajectory "
      f"prices the tracker. Decomposition: boxes fitted to the voxels and depth, "
      + _selection_words(r["decompose"]) + ", " + _refine_words(r["decompose"])
      + ("" if r["decompose"]["refine"] else
         " (+Sample; Levenberg-Marquardt refinement after it is the +Refine rows)")
      + ("" if not r["validation"] else
         f"; the headline's method was chosen on validation towers of seed "
         f"{r['validation']['seed']} (tracked RMSE +Sample "
         f"{r['validation']['density_rmse_tracked']['sample']:.1f}, +Refine "
         f"{r['validation']['density_rmse_tracked']['refine']:.1f}: "
         f"{r['validation']['report']})" + _search_words(r["validation"].get("search")))
      + ". Density RMSE in "
      "slots (100 kg/m³) of the box nearest each true block (two blocks may share one "
      "box, then both take its density and the mass ratio of a 2-block tower is 1), 95 % "
      "bootstrap intervals over towers.", "",
      "## Targets", "",
      "| target | ours (tracked video) | goal | paper | met |", "|---|--:|--:|--:|:-:|",
      f"| density RMSE, all towers | {_ci(tracked, 'rmse_all')} | ≤ 10 | 18.7 | "
      f"{met(tracked.get('rmse_all', 99) <= 10)} |",
      f"| density RMSE, 2-block towers | {_ci(tracked, 'rmse_2_blocks')} | ≤ 5 | 10.1 | "
      f"{met(tracked.get('rmse_2_blocks', 99) <= 5)} |",
      f"| which is heavier, Pearson r (levels 2^k) | {h['tracked']['pearson_levels']:.3f} | "
      f"≥ 0.95 | 0.90 | {met(h['tracked']['pearson_levels'] >= 0.95)} |",
      f"| tracking, median position error | {t['position_mm_median']:.2f} mm | ≤ 2 mm | – | "
      f"{met(t['position_mm_median'] <= 2)} |",
      f"| tracking, median rotation error | {t['rotation_deg_median']:.2f}° | ≤ 0.5° | – | "
      f"{met(t['rotation_deg_median'] <= 0.5)} |", "",
      "## Density", "",
      "| trajectory read | towers | RMSE all | 2 blocks | 3 blocks | 4 blocks | top-1 (%) | "
      "material right (%) |", "|---|--:|--:|--:|--:|--:|--:|--:|"]
  for way, row in d.items():
    lines.append(f"| {way} | {row['towers']} | {_ci(row, 'rmse_all')} | "
                 f"{_ci(row, 'rmse_2_blocks')} | {_ci(row, 'rmse_3_blocks')} | "
                 f"{_ci(row, 'rmse_4_blocks')} | {row['top1_percent']:.1f} | "
                 f"{row['material_accuracy_percent']:.1f} |")
  lines += ["", "Towers whose clip could not be tracked (see Tracking) have no tracked row; "
            "'true, tracked towers only' is the true-trajectory row on the same towers as "
            "the tracked one.", "",
            f"Random guessing: {rg['four_materials']:.1f} among the four materials, "
            f"{rg['hundred_slots']:.1f} among all 100 slots (the paper's random guess: 40.8).",
            "", "## Which block is heavier (2-block towers)", "",
            "The mass of the upper block over the lower one, on the paper's answer scale "
            "{2^k, k = -4..4} (log2 rounded and clipped) and as plain log2.", "",
            "| trajectory read | towers | Pearson r, levels | Pearson r, log2 | same level (%) | "
            "heavier block right (%) |", "|---|--:|--:|--:|--:|--:|"]
  for way, row in h.items():
    lines.append(f"| {way} | {row['towers']} | {row['pearson_levels']:.3f} | "
                 f"{row['pearson_log2']:.3f} | {row['same_level_percent']:.1f} | "
                 f"{row['heavier_right_percent']:.1f} |")
  lines += ["", f"![which is heavier]({figure})", "", "## Tracking", "",
            f"{t['tracked']} of {t['clips']} clips tracked; median over clips of each clip's "
            f"median error: {t['position_mm_median']:.2f} mm (90th percentile of clips "
            f"{t['position_mm_p90_of_clip_medians']:.2f} mm), {t['rotation_deg_median']:.2f}°."]
  if t["failures"]:
    lines += ["", "Failures: " + "; ".join(t["failures"][:5])]
  if r["steps"]["steps"]:
    lines += ["", "## Steps", ""] + pipeline_steps.steps_md(r["steps"])
  return "\n".join(lines) + "\n"
