"""The block model's learning curve over the paper pipeline's 3,000 steps and a
continuation: training and validation density loss and validation top-1 by step.

  python experiments/blocks_longer/plot.py \
      --first=experiments/results/blocks_runs/full.metrics.jsonl \
      --then=experiments/results/blocks_longer_2026-11-29/metrics.jsonl \
      --out=experiments/results/blocks_longer_2026-11-29/learning_curve.png
"""

import json

import matplotlib
from absl import app, flags

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

flags.DEFINE_string("first", "", "metrics.jsonl of the run continued from.")
flags.DEFINE_string("then", "", "metrics.jsonl of the continuation (steps counted on).")
flags.DEFINE_string("out", "", "The PNG.")
FLAGS = flags.FLAGS


def rows(path: str, offset: int):
  with open(path) as f:
    out = [json.loads(line) for line in f if line.strip()]
  train = [(r["step"] + offset, r["density_loss"]) for r in out
           if "split" not in r and "density_loss" in r and r.get("phase") == 2]
  val = [(r["step"] + offset, r["density_loss"], r["density_top1"]) for r in out
         if r.get("split") == "val"]
  return train, val


def main(argv):
  del argv
  first_train, first_val = rows(FLAGS.first, 0)
  offset = max(s for s, *_ in first_train + first_val)
  then_train, then_val = rows(FLAGS.then, offset)
  fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.6))
  for (tr, va), name, color in (((first_train, first_val), "paper pipeline", "C0"),
                                ((then_train, then_val), "continued (lr 5e-4)", "C1")):
    ax.plot(*zip(*tr), color=color, lw=1, alpha=0.6, label=f"{name}: train")
    ax.plot([s for s, *_ in va], [v[1] for v in va], "o-", color=color,
            label=f"{name}: validation")
    bx.plot([s for s, *_ in va], [v[2] for v in va], "o-", color=color, label=name)
  ax.set(xlabel="step", ylabel="density loss (nats per object)", ylim=(6, 12))
  bx.set(xlabel="step", ylabel="validation density top-1 (%)")
  bx.axhline(16.1, color="0.5", ls="--", lw=1, label="paper's PPD (full), test")
  ax.legend(fontsize=7)
  bx.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(FLAGS.out, dpi=110)


if __name__ == "__main__":
  app.run(main)
