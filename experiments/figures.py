"""Paper Figs. 7 and 8 for block towers: learning curves and density confusion matrices.

  python experiments/figures.py --root=out/blocks_runs --out=experiments/results/tiny

Reads the variants that table2.py trained and evaluated under ROOT: writes
OUT/learning_curves.png (training and validation losses and validation density top-1 of
every variant) and OUT/confusion.png (the full model's true × predicted density slots:
plain, +Sample and, if evaluated, +Refine).
"""

from __future__ import annotations

import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from absl import app, flags  # noqa: E402

from ppdjax.plots import plot_confusion  # noqa: E402

flags.DEFINE_string("root", "out/blocks_runs", "Where table2.py trained and evaluated.")
flags.DEFINE_string("out", "experiments/results/tiny", "Where the figures go.")
FLAGS = flags.FLAGS
VARIANTS = ("full", "no_trajectory", "no_image", "no_voxels")


def learning_curves(root: str, path: str) -> str:
  fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
  for i, v in enumerate(VARIANTS):
    file = os.path.join(root, v, "metrics.jsonl")
    if not os.path.exists(file):
      continue
    with open(file) as f:
      rows = [json.loads(line) for line in f if line.strip()]
    train = [r for r in rows if r.get("split", "train") == "train"]
    val = [r for r in rows if r.get("split") == "val"]
    c = f"C{i}"
    axes[0].plot([r["step"] for r in train], [r["density_loss"] for r in train], color=c,
                 alpha=0.6, label=f"{v} train")
    axes[0].plot([r["step"] for r in val], [r["density_loss"] for r in val], "o--", color=c,
                 label=f"{v} val")
    axes[1].plot([r["step"] for r in train], [r["geometry_loss"] for r in train], color=c,
                 label=v)
    axes[2].plot([r["step"] for r in val], [r["density_top1"] for r in val], "o-", color=c,
                 label=v)
  axes[0].set(title="density loss", yscale="log", xlabel="step")
  axes[1].set(title="geometry loss (train)", yscale="log", xlabel="step")
  axes[2].set(title="validation density top-1 (%)", xlabel="step")
  for ax in axes:
    ax.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return path


def main(argv):
  del argv
  os.makedirs(FLAGS.out, exist_ok=True)
  print("wrote", learning_curves(FLAGS.root, os.path.join(FLAGS.out, "learning_curves.png")))
  path = os.path.join(FLAGS.root, "full", "eval", "results.json")
  if not os.path.exists(path):
    raise SystemExit(f"{path} is missing: run experiments/table2.py first")
  with open(path) as f:
    confusion = json.load(f)["confusion"]
  print("wrote", plot_confusion(confusion, os.path.join(FLAGS.out, "confusion.png")))


if __name__ == "__main__":
  app.run(main)
