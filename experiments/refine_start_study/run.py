"""Where +Refine starts: the candidate closest over all steps or over the selection horizon
(CPU only; reads two evaluations of the same objects).

  python experiments/refine_start_study/run.py \
      --pair val=DIR_ALL,DIR_32 --pair test=DIR_ALL,DIR_32 \
      --out=experiments/results/refine_start_2026-11-27

Each pair is two evaluations (`python -m ppdjax.evaluate ... --keep_records --out=DIR`) of
the same objects with the same seed and selection, differing only in `--refine_horizon`:
the first refines from the candidate closest over the whole trajectory (0), the second
from the one closest over the first N steps (+Sample's own pick at τ = 0 with
`--selection_horizon=N`). The script checks that their +Sample rows agree object by
object (the same candidates were simulated), then writes, per split, both +Refine rows and
+Sample with 95 % intervals over whole towers and the paired change (second minus first)
from one tower bootstrap drawing both: OUT/results.md and results.json.

A split's records are its objects in the evaluation's order; an object's tower is its
index in the split divided by the configurations per tower (with `--subset=spread`, the
indices `batches.evaluation_objects` chose). The script checks the grouping: its
intervals for each row must be those results.json drew over the dataset's tower ids.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
from absl import app, flags

from ppdjax.infer import partial
from ppdjax.infer.batches import evaluation_objects
from ppdjax.infer.markdown import with_ci

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from selection_horizon_study.run import (check_intervals, paired_difference,  # noqa: E402
                                         row_metrics, tower_groups)

FLAGS = flags.FLAGS

SAMPLE, REFINE = "PPD+Fit+Sample", "PPD+Fit+Sample+Refine"
COUNTS = ("top1", "top5", "top10", "sq_err", "count")
KEYS = ("top1", "top5", "top10", "rmse", "mae")

def read(folder: str) -> tuple[dict, dict]:
  """(results.json, records) of an evaluation kept with --keep_records."""
  for need in ("results.json", os.path.join("partial", partial.RECORDS_FILE)):
    if not os.path.exists(os.path.join(folder, need)):
      raise SystemExit(f"{folder} has no {need}: an evaluation's output with --keep_records "
                       "is expected")
  with open(os.path.join(folder, "results.json")) as f:
    return json.load(f), partial.saved_records(os.path.join(folder, "partial"))


def tower_ids(results: dict, n: int, configs_per_tower: int) -> np.ndarray:
  """(n,) tower of each record: a split keeps each tower's configurations in a row, so an
  object's tower is its index in the split over the configurations per tower."""
  towers = int(results.get("geometries") or 0)
  if results.get("subset") == "spread" and n < towers * configs_per_tower:
    return evaluation_objects(towers * configs_per_tower, n, "spread") // configs_per_tower
  return tower_groups(results, n)


def _row(rec: dict, row: str) -> tuple[dict, np.ndarray]:
  """(counts, MAE) of a Table 2 row in an evaluation's records."""
  return ({k: np.asarray(rec[("counts", row, k)]) for k in COUNTS},
          np.asarray(rec[("mae", row)], np.float64))


def row_of(rec: dict, row: str, groups: np.ndarray) -> dict:
  """A row's metrics with 95 % intervals over the towers and its Table 5."""
  return row_metrics(*_row(rec, row), np.asarray(rec[("blocks",)]), groups)


def paired_change(first: dict, second: dict, groups: np.ndarray, row: str,
                  resamples: int = 1000) -> dict:
  """The row's top-k, RMSE and MAE in `second` minus in `first`, on the same objects, with
  95 % intervals from one tower bootstrap drawing both."""
  return paired_difference(_row(first, row), _row(second, row), groups, KEYS, resamples)


def check_same_candidates(first: dict, second: dict, where: str) -> None:
  """Raises ValueError unless both evaluations' +Sample picks agree object by object (the
  same slots; the same MAE within a micrometre: the two simulated the candidates in
  batches of another size, whose float32 sums differ in the last digits)."""
  for key in (("guess", SAMPLE), ("true_slot",), ("mae", SAMPLE)):
    a, b = np.asarray(first[key]), np.asarray(second[key])
    same = (np.allclose(a, b, rtol=0, atol=1e-3) if key[0] == "mae"
            else np.array_equal(a, b)) if a.shape == b.shape else False
    if not same:
      raise ValueError(f"{where}: the two evaluations' {'/'.join(map(str, key))} differ: "
                       "they did not simulate the same candidates of the same objects")


def study_split(first_dir: str, second_dir: str, configs_per_tower: int) -> dict:
  """Both +Refine rows, +Sample and the paired change of one split."""
  (res_a, rec_a), (res_b, rec_b) = read(first_dir), read(second_dir)
  h_a, h_b = int(res_a.get("refine_horizon", 0)), int(res_b.get("refine_horizon", 0))
  if h_a != 0 or h_b == 0:
    raise ValueError(f"{first_dir} must refine from all steps and {second_dir} from a "
                     f"horizon; they refine from {h_a} and {h_b} (0: all)")
  check_same_candidates(rec_a, rec_b, f"{first_dir} and {second_dir}")
  n = len(rec_a[("blocks",)])
  groups = tower_ids(res_a, n, configs_per_tower)
  rows = {"+Sample": row_of(rec_a, SAMPLE, groups),
          "+Refine from all steps": row_of(rec_a, REFINE, groups),
          f"+Refine from {h_b} steps": row_of(rec_b, REFINE, groups)}
  for (label, results) in (("+Sample", res_a), ("+Refine from all steps", res_a),
                           (f"+Refine from {h_b} steps", res_b)):
    name = SAMPLE if label == "+Sample" else REFINE
    check_intervals(rows[label]["ci95"], results["table2"][name]["ci95"], name)
  return {"objects": n, "towers": int(res_a["geometries"]), "horizon": h_b, "rows": rows,
          "change": paired_change(rec_a, rec_b, groups, REFINE),
          "commands": [res_a["command"], res_b["command"]]}


def markdown(study: dict) -> str:
  lines = ["# Where +Refine starts: closest over all steps or over the selection horizon",
           "", "```", *study["command_lines"], "```", ""]
  for name, s in study["splits"].items():
    lines += [f"## {name}: {s['objects']} objects, {s['towers']} towers", "",
              "| PPD (full)+Fit | top-1 | top-5 | top-10 | RMSE | MAE (mm) | Table 5: "
              + " / ".join(s["rows"]["+Sample"]["table5"]) + " blocks |",
              "|---|--:|--:|--:|--:|--:|---|"]
    for label, r in s["rows"].items():
      cells = [with_ci(r, "top1"), f"{r['top5']:.1f}", f"{r['top10']:.1f}",
               with_ci(r, "rmse", 2), f"{r['mae']:.2f}",
               " / ".join(f"{v:.2f}" for v in r["table5"].values())]
      lines.append(f"| {label} | " + " | ".join(cells) + " |")
    c = s["change"]
    lines += ["", f"Paired change, +Refine from {s['horizon']} steps minus from all steps "
              "(one bootstrap over towers drawing both): "
              + ", ".join(f"{k} {c[k]:+.2f} [{c['ci95_' + k][0]:+.2f}, "
                          f"{c['ci95_' + k][1]:+.2f}]" for k in KEYS) + ".", ""]
  return "\n".join(lines)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_multi_string("pair", None, "NAME=DIR_ALL,DIR_N: two evaluations of the same "
                            "objects, refining from all steps, then from the horizon.",
                            required=True)
  flags.DEFINE_integer("configs_per_tower", 8, "Density configurations of each tower (the paper "
                       "preset's 8).")
  flags.DEFINE_string("out", None, "Output folder.", required=True)


def main(argv):
  del argv
  study = {"splits": {}, "command_lines": []}
  for item in FLAGS.pair:
    name, _, dirs = item.partition("=")
    folders = dirs.split(",")
    if len(folders) != 2 or not all(folders):
      raise app.UsageError(f"--pair expects NAME=DIR_ALL,DIR_N, got {item!r}")
    try:
      study["splits"][name] = study_split(*folders, FLAGS.configs_per_tower)
    except ValueError as e:
      raise SystemExit(f"error: {e}") from e
    study["command_lines"] += study["splits"][name]["commands"]
    print(f"{name}: {study['splits'][name]['objects']} objects", flush=True)
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump(study, f, indent=1)
  with open(os.path.join(FLAGS.out, "results.md"), "w") as f:
    f.write(markdown(study))
  print(f"-> {FLAGS.out}")


if __name__ == "__main__":
  define_flags()
  app.run(main)
