"""The box-plane kernel's launch shape: rollouts and warps per program, timed side by side.

  python experiments/benchmarks/kernel_sweep.py --launches 32x4,32x2,128x8 --rollouts 2048,131072 \
      --out DIR

Each launch `BLOCKxWARPS` runs the same physics (`BoxPlaneSettings(kernel_block=,
kernel_warps=)`); the first named is the peer the others are timed against, in one
process on the same towers (512 random towers, tiled to the size: the rate does not depend
on which towers). Per launch and size: the first call's lowering and compilation (about
a minute and a half each on an H100; compiling launches in parallel processes did not
help there, they contend), the warm median of `--repeats` calls, the ratio to the peer,
and the gap of the trajectories to the peer's (mm). Needs a GPU (off one the kernel is
interpreted: correct, slow). Writes DIR/kernel_sweep.json and prints a markdown table.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.sim import rollout_mjx
from ppdjax.sim.box_plane import BoxPlaneSettings

DISTINCT_TOWERS = 512

flags.DEFINE_string("launches", "32x4,32x2,128x8", "Comma-separated BLOCKxWARPS; the first is "
                    "the peer.")
flags.DEFINE_string("rollouts", "2048,131072", "Comma-separated rollout counts, multiples of 4.")
flags.DEFINE_integer("repeats", 5, "Warm calls timed (median).")
flags.DEFINE_string("out", "kernel_sweep", "Output folder (DIR/kernel_sweep.json).")
FLAGS = flags.FLAGS


def _parse(launch: str) -> BoxPlaneSettings:
  block, warps = (int(x) for x in launch.split("x"))
  return BoxPlaneSettings(kernel="pallas", kernel_block=block, kernel_warps=warps)


def towers(n_rollouts: int):
  """n_rollouts // 4 towers (each under the four pushes): DISTINCT_TOWERS random ones, tiled."""
  count = n_rollouts // 4
  base = ppdjax.sample_towers(11, min(count, DISTINCT_TOWERS))
  reps = -(-count // len(base.valid))
  return jax.tree.map(lambda x: jnp.asarray(np.concatenate([x] * reps)[:count]), base)


def time_all(launches: list[str], sizes: list[int], repeats: int) -> list[dict]:
  """Every launch at every size: first call, warm median, ratio and gap to the peer."""
  rows, pushes = [], ppdjax.default_pushes()
  for n in sizes:
    prims = towers(n)
    peer_out, peer_s = None, None
    for launch in launches:
      settings = _parse(launch)
      t0 = time.perf_counter()
      compiled = jax.jit(lambda p, s=settings: rollout_mjx.simulate(p, pushes, settings=s)
                         ).lower(prims).compile()
      first = time.perf_counter() - t0
      out = np.asarray(jax.block_until_ready(compiled(prims)))
      warm = []
      for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(prims))
        warm.append(time.perf_counter() - t0)
      row = {"rollouts": n, "launch": launch, "warm_s": float(np.median(warm)),
             "compile_s": first}
      if peer_out is None:
        peer_out, peer_s = out, row["warm_s"]
      gap = np.linalg.norm(out[..., :3] - peer_out[..., :3], axis=-1).reshape(-1, out.shape[-2])
      row.update(x_peer=peer_s / row["warm_s"], gap_final_p90_mm=float(
          np.percentile(gap[:, -1], 90) * 1e3), gap_max_mm=float(gap.max() * 1e3),
          m_steps_per_s=n * out.shape[-2] / row["warm_s"] / 1e6)
      rows.append(row)
      print(f"| {n} | {launch} | {row['warm_s'] * 1e3:.1f} | {row['m_steps_per_s']:.1f} | "
            f"{row['x_peer']:.2f} | {first:.0f} | "
            f"{row['gap_final_p90_mm']:.4f} / {row['gap_max_mm']:.4f} |", flush=True)
  return rows


def main(argv):
  del argv
  sizes = [int(x) for x in FLAGS.rollouts.split(",")]
  launches = FLAGS.launches.split(",")
  for launch in launches:
    _parse(launch)  # a bad launch fails here, before any compilation
  print(f"device: {jax.devices()[0].device_kind}\n\n| rollouts | launch | warm (ms) | "
        "M steps/s | × peer | first call (s) | gap to peer: final p90 / max (mm) |\n"
        "|--:|---|--:|--:|--:|--:|--:|", flush=True)
  rows = time_all(launches, sizes, FLAGS.repeats)
  out = pathlib.Path(FLAGS.out)
  out.mkdir(parents=True, exist_ok=True)
  (out / "kernel_sweep.json").write_text(json.dumps(
      {"device": jax.devices()[0].device_kind, "command": " ".join(sys.argv), "rows": rows},
      indent=1))


if __name__ == "__main__":
  app.run(main)
