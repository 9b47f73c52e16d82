"""The block model's learning curve over the paper pipeline's 3,000 steps and its
continuations: training and validation density loss, validation top-1 and RMSE by step.

  R=experiments/results/blocks_longer_2026-11-29
  python experiments/blocks_longer/plot.py \
      --first=experiments/results/blocks_runs/full.metrics.jsonl \
      --then=$R/metrics.jsonl,$R/physics_stream.metrics.jsonl \
      "--labels=continued (lr 5e-4),continued + physics stream" \
      --out=$R/learning_curve.png
"""

import json

import matplotlib
from absl import app, flags

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

flags.DEFINE_string("first", "", "metrics.jsonl of the run continued from.")
flags.DEFINE_list("then", [], "metrics.jsonl of each continuation (steps counted on).")
flags.DEFINE_list("labels", [], "A name for each continuation.")
flags.DEFINE_string("out", "", "The PNG.")
FLAGS = flags.FLAGS


def rows(path: str, offset: int):
  with open(path) as f:
    out = [json.loads(line) for line in f if line.strip()]
  train = [(r["step"] + offset, r["density_loss"]) for r in out
           if "split" not in r and "density_loss" in r and r.get("phase") == 2]
  val = [(r["step"] + offset, r["density_loss"], r["density_top1"], r["density_rmse"])
         for r in out
         if r.get("split") == "val"]
  return train, val


def main(argv):
  del argv
  if len(FLAGS.labels) != len(FLAGS.then):
    raise app.UsageError(f"--labels names {len(FLAGS.labels)} runs, --then has "
                         f"{len(FLAGS.then)}")
  first_train, first_val = rows(FLAGS.first, 0)
  offset = max(s for s, *_ in first_train + first_val)
  runs = [((first_train, first_val), "paper pipeline")]
  runs += [(rows(path, offset), label) for path, label in zip(FLAGS.then, FLAGS.labels)]
  fig, (ax, bx, cx) = plt.subplots(1, 3, figsize=(14, 3.6))
  for i, ((tr, va), name) in enumerate(runs):
    color = f"C{i}"
    ax.plot(*zip(*tr), color=color, lw=1, alpha=0.6, label=f"{name}: train")
    steps = [s for s, *_ in va]
    ax.plot(steps, [v[1] for v in va], "o-", color=color, label=f"{name}: validation")
    bx.plot(steps, [v[2] for v in va], "o-", color=color, label=name)
    cx.plot(steps, [v[3] for v in va], "o-", color=color, label=name)
  ax.set(xlabel="step", ylabel="density loss (nats per object)", ylim=(6, 12))
  bx.set(xlabel="step", ylabel="validation density top-1 (%)")
  bx.axhline(16.1, color="0.5", ls="--", lw=1, label="paper's PPD (full), test")
  cx.set(xlabel="step", ylabel="validation density RMSE (slots)", ylim=(8, 14))
  cx.axhline(9.9, color="0.5", ls="--", lw=1, label="paper's PPD (full), test")
  for x in (ax, bx, cx):
    x.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(FLAGS.out, dpi=110)


if __name__ == "__main__":
  app.run(main)
