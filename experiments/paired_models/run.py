"""Two models evaluated on the same objects: each Table 2 row's change, paired (CPU only).

  python experiments/paired_models/run.py \
      --first=experiments/results/tools_runs_one_stack/eval_full/records \
      --second=experiments/results/tools_runs/eval_full/records \
      --configs_per_object=8 --out=experiments/results/tools_paired_density_branch

Reads the per-object records two evaluations kept (`--keep_records`; the tools pipeline
keeps them), checks that they describe the same objects (the true slots, object by
object), and writes for the rows both hold the second's top-k, RMSE and trajectory MAE
minus the first's, and shape F1's change, each with a 95 % interval from one bootstrap
that draws whole geometries (`--configs_per_object` consecutive records share one: a
tower's or a tool's density configurations) for both models at once. Such a paired
interval is narrower than the two rows' intervals side by side: it leaves out how hard
the drawn objects are, which both models share. OUT/results.{md,json}.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.eval import partial

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from selection_horizon_study.run import paired_difference  # noqa: E402

FLAGS = flags.FLAGS

COUNTS = ("top1", "top5", "top10", "sq_err", "count")
KEYS = ("top1", "top5", "top10", "rmse", "mae")
ROWS = ("PPD", "PPD+Sample", "PPD+Fit", "PPD+Fit+Sample", "PPD+True boxes+Sample")


def read(folder: str) -> dict:
  if not os.path.exists(os.path.join(folder, partial.RECORDS_FILE)):
    raise SystemExit(f"{folder} holds no {partial.RECORDS_FILE}: an evaluation's records "
                     "(--keep_records) are expected")
  return partial.saved_records(folder)


def row(rec: dict, name: str) -> tuple[dict, np.ndarray]:
  """(counts, MAE) of a Table 2 row in an evaluation's records."""
  return ({k: np.asarray(rec[("counts", name, k)]) for k in COUNTS},
          np.asarray(rec[("mae", name)], np.float64))


def f1(rec: dict, idx: np.ndarray) -> float:
  """Shape F1 (%) over the records `idx`, from their matched / predicted / true counts."""
  return metrics.f1_from_counts(*(np.asarray(rec[("shape", k)])[idx]
                                  for k in ("matched", "predicted", "true")))


def compare(first: dict, second: dict, groups: np.ndarray, resamples: int = 1000) -> dict:
  """Per row both hold: the paired change of top-k, RMSE and MAE; and shape F1's."""
  if not (np.array_equal(np.asarray(first[("true_slot",)]), np.asarray(second[("true_slot",)]))
          and len(groups) == len(first[("true_slot",)])):
    raise ValueError("the two evaluations' true slots differ: they are not of the same "
                     "objects in the same order")
  names = [n for n in ROWS if ("mae", n) in first and ("mae", n) in second]
  out = {"objects": len(groups), "geometries": int(len(np.unique(groups))), "rows": {}}
  for name in names:
    out["rows"][name] = paired_difference(row(first, name), row(second, name), groups, KEYS,
                                          resamples)
  n = len(groups)
  diff = lambda i: f1(second, i) - f1(first, i)  # noqa: E731
  out["shape_f1"] = {"first": f1(first, np.arange(n)), "second": f1(second, np.arange(n)),
                     "change": diff(np.arange(n)),
                     "ci95": list(metrics.bootstrap_interval(diff, n, resamples=resamples,
                                                             groups=groups))}
  return out


def markdown(study: dict, command: str) -> str:
  lines = ["# Two models on the same objects: second minus first, paired", "", "```",
           command, "```", "",
           f"{study['objects']} objects, {study['geometries']} geometries; 95 % intervals "
           "from one bootstrap over geometries drawing both models.", "",
           "| row | top-1 | top-5 | top-10 | RMSE (slots) | MAE (mm) |",
           "|---|--:|--:|--:|--:|--:|"]
  for name, d in study["rows"].items():
    cell = lambda k, fmt="+.1f": (  # noqa: E731
        f"{d[k]:{fmt}} [{d['ci95_' + k][0]:{fmt}}, {d['ci95_' + k][1]:{fmt}}]")
    lines.append(f"| {name} | {cell('top1')} | {cell('top5')} | {cell('top10')} | "
                 f"{cell('rmse', '+.2f')} | {cell('mae')} |")
  s = study["shape_f1"]
  lines += ["", f"Shape F1: {s['first']:.1f} → {s['second']:.1f}, change {s['change']:+.1f} "
            f"[{s['ci95'][0]:+.1f}, {s['ci95'][1]:+.1f}].", ""]
  return "\n".join(lines)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_string("first", None, "The first evaluation's records folder.", required=True)
  flags.DEFINE_string("second", None, "The second's, of the same objects.", required=True)
  flags.DEFINE_integer("configs_per_object", 8, "Consecutive records that share a geometry (the "
                       "presets' 8).")
  flags.DEFINE_string("out", None, "Output folder.", required=True)


def main(argv):
  del argv
  if FLAGS.configs_per_object < 1:
    raise app.UsageError("--configs_per_object must be >= 1")
  first, second = read(FLAGS.first), read(FLAGS.second)
  n = len(first[("true_slot",)])
  if n % FLAGS.configs_per_object:
    raise app.UsageError(f"{n} records are not whole geometries of {FLAGS.configs_per_object}")
  try:
    study = compare(first, second, np.arange(n) // FLAGS.configs_per_object)
  except ValueError as e:
    raise SystemExit(f"error: {e}") from e
  command = (f"python experiments/paired_models/run.py --first={FLAGS.first} "
             f"--second={FLAGS.second} --configs_per_object={FLAGS.configs_per_object} "
             f"--out={FLAGS.out}")
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump({**study, "command": command}, f, indent=1)
  text = markdown(study, command)
  with open(os.path.join(FLAGS.out, "results.md"), "w") as f:
    f.write(text)
  print(text)


if __name__ == "__main__":
  define_flags()
  app.run(main)
