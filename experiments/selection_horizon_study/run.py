"""+Sample's selection horizon, chosen on validation and checked on test (CPU only).

  python experiments/selection_horizon_study/run.py \
      --eval val=DIR_VAL --eval test=DIR_TEST --out=experiments/results/selection_horizon_2026-11-27

Each DIR is an evaluation's output (`python -m ppdjax.evaluate ... --config.eval.horizon_sweep=True
--keep_records --out=DIR`): its results.json and the per-object records in DIR/partial
(`partial.saved_records`). The horizon sweep records every +Sample row's pick at each τ
for the distance over the first 16, 32, 64, 128 or all 256 steps, from the same simulated
candidates (`rows._sweep`), so no horizon costs a rollout. This reads them at the
evaluation's own τ and writes, per split, row and horizon: top-1/5/10, RMSE, MAE, Table 5
by block count, with 95 % intervals over whole towers; the choice (the best top-1 on the
first split, ties to the lower RMSE); OUT/results.md, results.json and horizons.png.

A split's objects are its towers' configurations in a row (`generation.generate_shard`
repeats each tower `configs_per_tower` times, and a split keeps their order), so the
records' k-th tower is objects [k·c, (k+1)·c) with c = objects / towers from results.json;
the script checks it: at the evaluation's own horizon its intervals must be those of
results.json, which the evaluation drew over the dataset's tower ids.
"""

from __future__ import annotations

import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position
from absl import app, flags  # pylint: disable=wrong-import-position

from ppdjax import metrics  # pylint: disable=wrong-import-position
from ppdjax.eval import partial  # pylint: disable=wrong-import-position
from ppdjax.report import tables
from ppdjax.report.markdown import with_ci  # pylint: disable=wrong-import-position

FLAGS = flags.FLAGS

ROWS = ("PPD+Fit+Sample", "PPD+Sample")
COUNTS = ("top1", "top5", "top10", "sq_err", "count")


def tower_groups(results: dict, n: int) -> np.ndarray:
  """(n,) tower index of each record: configurations of a tower are contiguous."""
  towers = int(results.get("geometries") or 0)
  if towers <= 0 or n % towers:
    raise ValueError(f"{n} records cannot be {towers} towers of equal configurations: "
                     "is this a whole-split evaluation with intervals over towers?")
  return np.arange(n) // (n // towers)


def horizon_rows(rec: dict, groups: np.ndarray, tau: float, resamples: int = 1000) -> dict:
  """{row: {horizon: metrics with ci95 and Table 5}} from the records' horizon sweep."""
  horizons = sorted({k[2] for k in rec if k[0] == "hsweep"}, key=lambda h: h or 10**9)
  if not horizons:
    raise ValueError("the records hold no horizon sweep: evaluate with --config.eval.horizon_sweep=True")
  blocks = np.asarray(rec[("blocks",)])
  out = {}
  for row in ROWS:
    if ("hsweep", row, horizons[0], tau, "top1") not in rec:
      continue
    out[row] = {str(h): row_metrics(*_sweep_row(rec, row, h, tau), blocks, groups,
                                    resamples) for h in horizons}
  return out


def _sweep_row(rec: dict, row: str, horizon: int, tau: float) -> tuple[dict, np.ndarray]:
  """(counts, MAE) of a row's pick at `horizon` and τ from the records' horizon sweep."""
  return ({k: np.asarray(rec[("hsweep", row, horizon, tau, k)]) for k in COUNTS},
          np.asarray(rec[("hsweep", row, horizon, tau, "mae")], np.float64))


def row_metrics(counts: dict, mae: np.ndarray, blocks: np.ndarray, groups: np.ndarray,
                resamples: int = 1000) -> dict:
  """A row's top-k, RMSE and MAE with 95 % intervals over `groups`, and its Table 5."""
  m = tables.np_metrics(counts, np.arange(len(mae)))
  m["mae"] = float(mae.mean())
  m["ci95"] = {k: list(v) for k, v in
               tables.intervals(counts, mae, resamples=resamples, groups=groups).items()}
  m["table5"], t5_ci = tables.by_blocks(counts, blocks, groups=groups)
  m["table5_ci95"] = {b: list(v) for b, v in t5_ci.items()}
  return m


def paired_difference(first: tuple, second: tuple, groups: np.ndarray, keys,
                      resamples: int = 1000) -> dict:
  """`keys` (top-k, "rmse", "mae") of `second` minus `first`, each a row's (counts, MAE)
  on the same objects, with 95 % intervals from one bootstrap over `groups` drawing both
  (the change's own uncertainty, narrower than the two rows' intervals side by side)."""
  value = lambda row, key, i: (float(row[1][i].mean()) if key == "mae"  # noqa: E731
                               else tables.np_metrics(row[0], i)[key])
  n = len(groups)
  out = {}
  for key in keys:
    diff = lambda i, key=key: value(second, key, i) - value(first, key, i)  # noqa: E731
    out[key] = diff(np.arange(n))
    out["ci95_" + key] = list(metrics.bootstrap_interval(diff, n, resamples=resamples,
                                                         groups=groups))
  return out


def paired_change(rec: dict, groups: np.ndarray, row: str, tau: float, horizon: int,
                  resamples: int = 1000) -> dict:
  """top-1 and RMSE at `horizon` minus at all steps, on the same objects, with 95 %
  intervals from one tower bootstrap drawing both."""
  return paired_difference(_sweep_row(rec, row, 0, tau), _sweep_row(rec, row, horizon, tau),
                           groups, ("top1", "rmse"), resamples)


def check_intervals(ours: dict, theirs: dict, what: str) -> None:
  """Raises ValueError unless the top-1 and RMSE intervals `ours` (from the records) are
  `theirs` (results.json's, drawn over the dataset's tower ids): the same bootstrap over
  the same towers, so the records' tower order holds."""
  for key in ("top1", "rmse"):
    if key in theirs and not np.allclose(ours[key], theirs[key], rtol=0, atol=1e-9):
      raise ValueError(f"{what} {key}: interval {ours[key]} from the records, "
                       f"{theirs[key]} in results.json: the records are not in the "
                       "evaluation's tower order")


def check_grouping(rows: dict, results: dict) -> None:
  """`check_intervals` of each row at the evaluation's own horizon."""
  horizon = str(results.get("selection_horizon") or 0)
  for row, by_h in rows.items():
    check_intervals(by_h[horizon]["ci95"], results["table2"].get(row, {}).get("ci95", {}),
                    f"{row} at {horizon} steps")


def choose(rows: dict) -> str:
  """The horizon with the best top-1 (ties: the lower RMSE)."""
  return min(rows, key=lambda h: (-round(rows[h]["top1"], 1), rows[h]["rmse"]))


def markdown(study: dict) -> str:
  lines = ["# +Sample's selection horizon: the distance over the first N steps", "",
           "```", *study["commands"], "```", "",
           f"Chosen on `{study['choose_on']}` ({study['row']}, best top-1, ties to the lower "
           f"RMSE): **{study['chosen']} steps** (0: all 256). τ = {study['tau']}. "
           "95 % bootstrap intervals over whole towers.", ""]
  lines += [f"{study['row']} at {study['chosen']} steps minus all steps, same objects (paired "
            "tower bootstrap):", ""]
  for split, s in study["splits"].items():
    c = s["change"]
    lines.append(f"- `{split}`: top-1 {c['top1']:+.2f} [{c['ci95_top1'][0]:+.2f}, "
                 f"{c['ci95_top1'][1]:+.2f}] points, RMSE {c['rmse']:+.3f} "
                 f"[{c['ci95_rmse'][0]:+.3f}, {c['ci95_rmse'][1]:+.3f}] slots")
  lines.append("")
  for split, s in study["splits"].items():
    lines += [f"## `{split}` ({s['objects']} objects, {s['towers']} towers)", ""]
    for row, by_h in s["rows"].items():
      lines += [f"### {row}", "",
                "| steps | top-1 | top-5 | top-10 | RMSE | MAE (mm) | Table 5: 2 / 3 / 4 / 5 "
                "blocks | 2 blocks, 95 % |", "|--:|--:|--:|--:|--:|--:|---|--:|"]
      for h, m in by_h.items():
        t5 = " / ".join(f"{m['table5'][b]:.2f}" for b in sorted(m["table5"]))
        two = m["table5_ci95"].get("2")
        lines.append(f"| {'all' if h == '0' else h} | {with_ci(m, 'top1')} | {m['top5']:.1f} | "
                     f"{m['top10']:.1f} | {with_ci(m, 'rmse', 2)} | {m['mae']:.2f} | {t5} | "
                     + (f"[{two[0]:.2f}, {two[1]:.2f}]" if two else "–") + " |")
      lines.append("")
  return "\n".join(lines)


def plot(study: dict, path: str) -> None:
  fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
  for split, s in study["splits"].items():
    by_h = s["rows"][study["row"]]
    hs = list(by_h)
    x = np.arange(len(hs))
    for ax, key in zip(axes, ("top1", "rmse")):
      y = [by_h[h][key] for h in hs]
      ci = np.array([by_h[h]["ci95"][key] for h in hs])
      ax.errorbar(x, y, yerr=[np.array(y) - ci[:, 0], ci[:, 1] - np.array(y)], marker="o",
                  capsize=3, label=split)
      ax.set_xticks(x, [h if h != "0" else "all" for h in hs])
  axes[0].set(xlabel="steps the distance covers", ylabel="top-1 (%)", title=study["row"])
  axes[1].set(xlabel="steps the distance covers", ylabel="density RMSE (slots)")
  axes[0].legend()
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_multi_string("eval", None, "NAME=DIR: an evaluation's output folder; the first "
                            "chooses the horizon.", required=True)
  flags.DEFINE_enum("row", "PPD+Fit+Sample", ROWS, "The +Sample row read.")
  flags.DEFINE_string("out", None, "Output folder.", required=True)


def main(argv):
  del argv
  study = {"row": FLAGS.row, "splits": {}, "commands": []}
  for item in FLAGS.eval:
    name, _, folder = item.partition("=")
    if not folder:
      raise app.UsageError(f"--eval expects NAME=DIR, got {item!r}")
    for need in ("results.json", os.path.join("partial", partial.RECORDS_FILE)):
      if not os.path.exists(os.path.join(folder, need)):
        raise SystemExit(f"{folder} has no {need}: an evaluation's output with "
                         "--config.eval.horizon_sweep=True --keep_records is expected")
    with open(os.path.join(folder, "results.json")) as f:
      results = json.load(f)
    rec = partial.saved_records(os.path.join(folder, "partial"))
    n = len(rec[("blocks",)])
    tau = float(results["prior_weight"])
    study.setdefault("tau", tau)
    if tau != study["tau"]:
      raise SystemExit(f"{folder} selects at τ = {tau}, the first evaluation at {study['tau']}")
    study["commands"].append(results["command"])
    groups = tower_groups(results, n)
    rows = horizon_rows(rec, groups, tau)
    check_grouping(rows, results)
    study["splits"][name] = {"objects": n, "towers": int(results["geometries"]), "rows": rows}
    if "chosen" not in study:  # the first split chooses
      study["choose_on"] = name
      study["chosen"] = int(choose(study["splits"][name]["rows"][FLAGS.row]))
    study["splits"][name]["change"] = paired_change(rec, groups, FLAGS.row, tau, study["chosen"])
    print(f"{name}: {n} objects read from {folder}", flush=True)
  first = study["choose_on"]
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump(study, f, indent=1)
  with open(os.path.join(FLAGS.out, "results.md"), "w") as f:
    f.write(markdown(study))
  plot(study, os.path.join(FLAGS.out, "horizons.png"))
  print(f"chosen on {first}: {study['chosen']} steps -> {FLAGS.out}")


if __name__ == "__main__":
  define_flags()
  app.run(main)
