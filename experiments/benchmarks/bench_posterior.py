"""What the posterior and the next push cost beside the `decompose` call they read.

  python experiments/benchmarks/bench_posterior.py --data=DIR --split=val --batch=8 \
      --out=experiments/results/bench_posterior_cpu.json

Peer: `make_decompose_fn(model)` with the model's own settings on `--batch` objects of a
dataset (warm, median of `--repeats`). Timed beside it, in the same process, on its
output: each box's posterior (`infer.posterior.density_posterior`, vmapped and jitted as
`decompose` runs it inside its own program: the share it adds), and
`make_next_push_fn(decompose)` choosing among the 64 default candidate pushes
(`--hypotheses` joint assignments simulated under each, the engine `decompose` uses).
Issue targets: the posterior <= 10 % of `decompose`; choosing a push <= one `decompose`.
"""

from __future__ import annotations

import json
import platform
import shlex
import sys
import time

import jax
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.conventions import OBS_KEYS
from ppdjax.infer import posterior, sampling
from ppdjax.report.provenance import write_provenance

flags.DEFINE_string("model", "assets/blocks_model", "The model.")
flags.DEFINE_string("data", "", "A dataset of towers the model never saw.")
flags.DEFINE_string("split", "val", "Its split.")
flags.DEFINE_integer("batch", 8, "Objects per call.")
flags.DEFINE_integer("repeats", 3, "Warm calls timed (median).")
flags.DEFINE_integer("hypotheses", 32, "Joint assignments simulated per candidate push.")
flags.DEFINE_string("out", "", "Write the figures as JSON here.")
FLAGS = flags.FLAGS


def timed(fn, repeats: int) -> float:
  """Median seconds of `repeats` warm calls (one call first, to compile)."""
  jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def main(_):
  ds = ppdjax.open_dataset(FLAGS.data, FLAGS.split)
  sample = ds.take(np.arange(FLAGS.batch))
  obs = {k: sample[k] for k in OBS_KEYS}
  decompose = ppdjax.make_decompose_fn(FLAGS.model)
  q = decompose.config.posterior
  key = jax.random.key(0)
  out = decompose(obs, key)
  belief = jax.jit(jax.vmap(lambda s, d, lg, v: posterior.density_posterior(
      s, d, sampling.log_prior(lg, s, v), v, scale=q.scale, level=q.level,
      identified_width=q.identified_width)))
  next_push = ppdjax.make_next_push_fn(decompose, hypotheses=FLAGS.hypotheses)
  rows = {
      "decompose_s": timed(lambda: decompose(obs, key).scores, FLAGS.repeats),
      "posterior_s": timed(lambda: belief(out.candidates, out.scores, out.density_logits,
                                          out.primitives.valid).probs, FLAGS.repeats),
      "next_push_s": timed(lambda: next_push(out).gain, FLAGS.repeats),
  }
  rows["posterior_share_of_decompose"] = rows["posterior_s"] / rows["decompose_s"]
  rows["next_push_over_decompose"] = rows["next_push_s"] / rows["decompose_s"]
  result = {**rows, "batch": FLAGS.batch, "hypotheses": FLAGS.hypotheses,
            "candidate_pushes": int(next_push.candidates.num), "model": FLAGS.model,
            "device": f"{jax.devices()[0].device_kind} x {jax.device_count()}",
            "machine": platform.machine(), "settings": decompose.config.to_dict(),
            "command": " ".join(shlex.quote(a) for a in ["python"] + sys.argv)}
  print(json.dumps(rows, indent=1))
  if FLAGS.out:
    with open(FLAGS.out, "w") as f:
      json.dump(result, f, indent=1)
    write_provenance(FLAGS.out, command=result["command"])


if __name__ == "__main__":
  app.run(main)
