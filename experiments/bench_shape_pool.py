"""Random tower shapes, three ways in one process: the NumPy tower generator as it was
until 2026-11-25 (the peer: each tower's corners through JAX, a round trip to the default
device), the generator now (corners in NumPy), and `baselines.random_shapes`
(`stream.sample_towers_jax`, jitted), which draws Table 4's shape pool.

  python experiments/bench_shape_pool.py --shapes 512 --repeats 5

The pool is drawn once a batch in the evaluation's reading thread; on the 2 x H100 machine
the generator took about 5 s of it, more than the batch's device work (4.5 s), so reading,
not the devices, set the evaluation's rate (benchmarks.md, "Two GPUs"). The dataset
generator draws its towers the same way, one at a time.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

import jax.numpy as jnp

from ppdjax import primitives
from ppdjax.dataset import towers
from ppdjax.infer import baselines


def _median_s(fn, repeats: int) -> float:
  jax.block_until_ready(fn(0))  # compiles the jitted one
  times = []
  for i in range(repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn(i + 1))
    times.append(time.perf_counter() - t)
  return float(np.median(times))


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument("--shapes", type=int, default=512)
  parser.add_argument("--repeats", type=int, default=5)
  args = parser.parse_args()
  numpy_corners = primitives.corners

  def jax_corners(p):  # the generator's corners as they were: jax.numpy on the device
    return numpy_corners(jax.tree.map(jnp.asarray, p))

  towers.corners = jax_corners
  before_s = _median_s(lambda i: towers.sample_towers(i, args.shapes).half_size, args.repeats)
  towers.corners = numpy_corners
  now_s = _median_s(lambda i: towers.sample_towers(i, args.shapes).half_size, args.repeats)
  jax_s = _median_s(lambda i: baselines.random_shapes(jax.random.key(i), args.shapes, 5),
                    args.repeats)
  print(f"{args.shapes} shapes on {jax.devices()[0].device_kind}: generator with JAX corners "
        f"(peer) {before_s * 1e3:.1f} ms; generator now {now_s * 1e3:.1f} ms "
        f"({before_s / now_s:.1f}x); random_shapes {jax_s * 1e3:.2f} ms "
        f"({before_s / jax_s:.0f}x)")


if __name__ == "__main__":
  main()
