"""The box-plane step's Pallas kernel beside its XLA reference, run side by side in one process.

  python experiments/benchmarks/bench_kernel.py --rollouts 2048,131072

For each size: random towers under the paper's four pushes, 256 steps, with
`BoxPlaneSettings(kernel="reference")` (the peer) and `kernel="pallas"` (one launch);
first call (compile) and median warm time, the ratio, and the kernel's gap to the
reference (mm: first 0.1 s p90 and max, all-steps median, final p50 / p90 / max).
Needs a GPU (off one, the kernel is interpreted: correct, slow).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.sim import rollout_mjx
from ppdjax.sim.box_plane import BoxPlaneSettings

flags.DEFINE_string("rollouts", "2048,131072", "Comma-separated rollout counts, multiples of 4.")
flags.DEFINE_integer("repeats", 5, "Warm calls timed (median).")
FLAGS = flags.FLAGS


def main(argv):
  del argv
  pushes = ppdjax.default_pushes()
  print(f"device: {jax.devices()[0].device_kind}")
  print("| rollouts | engine | first call (s) | warm (ms) | × reference |\n|--:|---|--:|--:|--:|")
  for n in [int(x) for x in FLAGS.rollouts.split(",")]:
    prims = jax.tree.map(jnp.asarray, ppdjax.sample_towers(11, n // 4))
    out, warm = {}, {}
    for kernel in ("reference", "pallas"):
      settings = BoxPlaneSettings(kernel=kernel)
      fn = jax.jit(lambda p, s=settings: rollout_mjx.simulate(p, pushes, settings=s))
      t0 = time.perf_counter()
      out[kernel] = np.asarray(jax.block_until_ready(fn(prims)))
      first = time.perf_counter() - t0
      times = []
      for _ in range(FLAGS.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(prims))
        times.append(time.perf_counter() - t0)
      warm[kernel] = float(np.median(times))
      print(f"| {n} | {kernel} | {first:.1f} | {warm[kernel] * 1e3:.1f} | "
            f"{warm['reference'] / warm[kernel]:.2f} |", flush=True)
    gap = np.linalg.norm(out["pallas"][..., :3] - out["reference"][..., :3], axis=-1) * 1e3
    gap = gap.reshape(-1, gap.shape[-1])
    print(f"\nkernel vs reference, {n} rollouts (mm): first 0.1 s p90 "
          f"{np.percentile(gap[:, :30].max(-1), 90):.4f} max {gap[:, :30].max():.4f}; "
          f"all-steps median {np.median(gap):.4f}; final p50 / p90 / max "
          f"{np.percentile(gap[:, -1], 50):.3f} / {np.percentile(gap[:, -1], 90):.3f} / "
          f"{gap[:, -1].max():.1f}\n", flush=True)


if __name__ == "__main__":
  app.run(main)
