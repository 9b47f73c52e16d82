"""Host loops that made a small JAX call per item, before and after, in one process.

  python experiments/benchmarks/bench_host_loops.py --repeats 5

Each row times the code as it was until 2026-11-25 (the peer: the item's arrays through
jax.numpy on the default device, a round trip per item) beside it now (NumPy on the host,
or one jitted call):
  * Table 4's shape pool, 512 random towers a batch (the evaluation's reading thread):
    the NumPy tower generator with JAX corners, the generator now (NumPy corners), and
    `baselines.random_shapes` (`stream.sample_towers_jax`, jitted), which the pool uses;
  * the renderer's rest position, once per rendered sample (`scene.rest_position`);
  * an evaluation batch's true slots in the reading thread (`primitives.bottom_to_top_order`;
    on a GPU its wait queued behind the batch being computed);
  * the shape F1's bootstrap interval, 1,000 resamples of 4,800 objects
    (`metrics.f1_from_counts`).
On the 2 x H100 machine the generator with JAX corners took 3.2 s for 512 towers, more
than an evaluation batch's device work (benchmarks.md, "Two GPUs").
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.dataset import towers
from ppdjax.eval import baselines
from ppdjax.sim import scene

flags.DEFINE_integer("shapes", 512, "Random towers in Table 4's shape pool.")
flags.DEFINE_integer("repeats", 5, "Timed calls (median).")
FLAGS = flags.FLAGS


def _median_s(fn, repeats: int) -> float:
  jax.block_until_ready(fn(0))  # compiles what is jitted
  times = []
  for i in range(repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn(i + 1))
    times.append(time.perf_counter() - t)
  return float(np.median(times))


def _row(name, before_s, now_s):
  print(f"| {name} | {before_s * 1e3:.1f} | {now_s * 1e3:.2f} | {before_s / now_s:.1f} |")


def main(argv):
  del argv
  on_device = lambda tree: jax.tree.map(jnp.asarray, tree)
  print(f"on {jax.devices()[0].device_kind}\n\n| work | before (ms) | now (ms) | × |\n"
        "|---|--:|--:|--:|")

  numpy_corners = towers.corners
  towers.corners = lambda p: numpy_corners(on_device(p))  # the generator as it was
  before = _median_s(lambda i: towers.sample_towers(i, FLAGS.shapes).half_size, FLAGS.repeats)
  towers.corners = numpy_corners
  now = _median_s(lambda i: towers.sample_towers(i, FLAGS.shapes).half_size, FLAGS.repeats)
  pool = _median_s(lambda i: baselines.random_shapes(jax.random.key(i), FLAGS.shapes, 5),
                   FLAGS.repeats)
  _row(f"{FLAGS.shapes} random towers: generator (JAX corners) -> generator (NumPy)",
       before, now)
  _row(f"{FLAGS.shapes} random towers: generator (JAX corners) -> random_shapes", before, pool)

  objects = [jax.tree.map(lambda x, i=i: x[i], towers.sample_towers(7, 256)) for i in range(256)]
  before = _median_s(lambda _: [np.asarray(scene.rest_position(on_device(p)))
                                for p in objects], FLAGS.repeats)
  now = _median_s(lambda _: [scene.rest_position(p) for p in objects], FLAGS.repeats)
  _row("rest position of 256 rendered samples", before, now)

  batch = towers.sample_towers(8, 64)
  before = _median_s(lambda _: baselines.true_slots(on_device(batch)), FLAGS.repeats)
  now = _median_s(lambda _: baselines.true_slots(batch), FLAGS.repeats)
  _row("true slots of a batch of 64 (bottom-to-top order)", before, now)

  rng = np.random.default_rng(0)
  m, p, t = (rng.integers(0, 5, 4800) for _ in range(3))

  def old_f1(i):
    total = float(jnp.sum(p[i]) + jnp.sum(t[i]))
    return 100.0 * 2.0 * float(jnp.sum(m[i])) / max(total, 1.0)

  before = _median_s(lambda _: metrics.bootstrap_interval(old_f1, 4800), 1)
  now = _median_s(lambda _: metrics.bootstrap_interval(
      lambda i: metrics.f1_from_counts(m[i], p[i], t[i]), 4800), 1)
  _row("shape F1's bootstrap, 4,800 objects", before, now)


if __name__ == "__main__":
  app.run(main)
