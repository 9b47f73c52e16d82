"""Paper Figs. 7 and 8 for block towers: learning curves and density confusion matrices.

  python experiments/figures.py --root=out/blocks_runs --out=experiments/results/tiny

Reads the variants that table2.py trained and evaluated under ROOT: writes
OUT/learning_curves.png (training and validation losses, validation shape F1 and
density top-1 of every variant) and OUT/confusion.png (the full model's true × predicted density slots:
plain, +Sample and, if evaluated, +Refine).
"""

from __future__ import annotations

import json
import os

from absl import app, flags

from ppdjax.plots import plot_confusion, plot_variant_curves

flags.DEFINE_string("root", "out/blocks_runs", "Where table2.py trained and evaluated.")
flags.DEFINE_string("out", "experiments/results/tiny", "Where the figures go.")
FLAGS = flags.FLAGS
VARIANTS = ("full", "no_trajectory", "no_image", "no_voxels")


def main(argv):
  del argv
  os.makedirs(FLAGS.out, exist_ok=True)
  print("wrote", plot_variant_curves(
      {v: os.path.join(FLAGS.root, v, "metrics.jsonl") for v in VARIANTS},
      os.path.join(FLAGS.out, "learning_curves.png")))
  path = os.path.join(FLAGS.root, "full", "eval", "results.json")
  if not os.path.exists(path):
    raise SystemExit(f"{path} is missing: run experiments/table2.py first")
  with open(path) as f:
    confusion = json.load(f)["confusion"]
  print("wrote", plot_confusion(confusion, os.path.join(FLAGS.out, "confusion.png")))


if __name__ == "__main__":
  app.run(main)
