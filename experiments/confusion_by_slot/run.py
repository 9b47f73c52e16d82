"""Where an evaluation's density errors are: its confusion matrix read by true slot range.

  python experiments/confusion_by_slot/run.py --results=A/results.json,B/results.json \
      --names=A,B --row=PPD --out=DIR

For each range of true slots (the materials' ranges of paper Table 1: wood 1-10, stone and
light metal 21-30, ceramic 31-60, heavy metal 71-100) and each evaluation: the boxes,
the share predicted exactly and within ±2 slots, the mean absolute error in slots and
relative to the true density, and the RMSE. CPU only; reads `confusion[row]` (true ×
predicted counts) of `ppdjax.evaluate`'s results.json. Writes DIR/confusion_by_slot.md
and .json.
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import app, flags

FLAGS = flags.FLAGS

RANGES = ((1, 10), (11, 20), (21, 30), (31, 60), (61, 70), (71, 100))  # slots, 1-based


def by_range(matrix) -> list[dict]:
  """Per true-slot range with boxes: counts and errors of a (100, 100) confusion matrix."""
  m = np.asarray(matrix, np.float64)
  if m.ndim != 2 or m.shape[0] != m.shape[1]:
    raise ValueError(f"a confusion matrix is square (true x predicted), got shape {m.shape}")
  slots = np.arange(m.shape[0])
  out = []
  for lo, hi in RANGES:
    rows = m[lo - 1:hi]
    count = rows.sum()
    if count == 0:
      continue
    true = slots[lo - 1:hi, None]
    err = np.abs(slots[None, :] - true)
    near = err <= 2
    out.append({"range": f"{lo}-{hi}", "boxes": int(count),
                "exact": 100.0 * float(np.trace(m[lo - 1:hi, lo - 1:hi])) / count,
                "within_2": 100.0 * float((rows * near).sum()) / count,
                "mean_abs_slots": float((rows * err).sum()) / count,
                "mean_abs_relative": 100.0 * float((rows * err / (true + 1)).sum()) / count,
                "rmse": float(np.sqrt((rows * err ** 2).sum() / count))})
  return out


def markdown(tables: dict, row: str) -> str:
  lines = [f"# The `{row}` row's density errors by true slot range", "",
           "| evaluation | true slots | boxes | exact (%) | within ±2 (%) | mean abs error "
           "(slots) | mean abs error (% of the density) | RMSE (slots) |",
           "|---|---|--:|--:|--:|--:|--:|--:|"]
  for name, rows in tables.items():
    for r in rows:
      lines.append(f"| {name} | {r['range']} | {r['boxes']} | {r['exact']:.1f} | "
                   f"{r['within_2']:.1f} | {r['mean_abs_slots']:.1f} | "
                   f"{r['mean_abs_relative']:.1f} | {r['rmse']:.1f} |")
  return "\n".join(lines) + "\n"


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_string("results", None, "Comma-separated results.json paths.", required=True)
  flags.DEFINE_string("names", "", "Comma-separated names (default: the paths).")
  flags.DEFINE_string("row", "PPD", "The Table 2 row whose matrix is read.")
  flags.DEFINE_string("out", None, "Output folder.", required=True)


def main(argv):
  del argv
  paths = FLAGS.results.split(",")
  names = FLAGS.names.split(",") if FLAGS.names else paths
  if len(names) != len(paths):
    raise app.UsageError(f"--names gives {len(names)} names for {len(paths)} results")
  tables = {}
  for name, path in zip(names, paths):
    if not os.path.exists(path):
      raise app.UsageError(f"no results file at {path}")
    confusion = json.load(open(path)).get("confusion", {})
    if FLAGS.row not in confusion:
      raise app.UsageError(f"{path} has no confusion matrix of row {FLAGS.row!r} (it has "
                           f"{', '.join(confusion) or 'none'})")
    tables[name] = by_range(confusion[FLAGS.row])
  os.makedirs(FLAGS.out, exist_ok=True)
  text = markdown(tables, FLAGS.row)
  with open(os.path.join(FLAGS.out, "confusion_by_slot.md"), "w") as f:
    f.write(text + "\n```\npython experiments/confusion_by_slot/run.py --results="
            + FLAGS.results + (f" --names={FLAGS.names}" if FLAGS.names else "")
            + f" --row={FLAGS.row} --out={FLAGS.out}\n```\n")
  with open(os.path.join(FLAGS.out, "confusion_by_slot.json"), "w") as f:
    json.dump(tables, f, indent=1)
  print(text)


if __name__ == "__main__":
  define_flags()
  app.run(main)
