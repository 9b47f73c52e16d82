"""+Joint's cost beside +Refine's (the peer) on one batch of dataset objects, in one process.

  python experiments/bench_refine.py --data=DATA --batch=64 --out=FILE.json

Takes the first --batch objects of a split (their true boxes, densities 30 % off, the
depth image and its camera) and times, warm, the evaluation's two refinements as it runs
them: `refine.refine_batch` (densities alone, 12 LM passes with K tangents) and
`joint.joint_batch` (faces and densities, 7K tangents, the depth image too) with
--at_once objects per vectorised group (the evaluation uses 64 on an accelerator, 8 on a
CPU). Cost depends on the
shapes and iteration count, not on the start. Prints a markdown table with the ratio to
+Refine.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset import storage
from ppdjax.infer.joint import joint_batch
from ppdjax.infer.refine import refine_batch
from ppdjax.primitives import bottom_to_top
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import settings_for


def timed(fn, repeats: int) -> tuple[float, float]:
  """(first call incl. compile, median of `repeats` warm calls), seconds."""
  t0 = time.perf_counter()
  jax.block_until_ready(fn())
  first = time.perf_counter() - t0
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return first, float(np.median(times))


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--data", required=True)
  parser.add_argument("--split", default="test")
  parser.add_argument("--batch", type=int, default=64)
  parser.add_argument("--at_once", default="8,64", help="+Joint group sizes to time")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--backend", default="mjx", choices=("mjx", "box_plane"),
                      help="the engine (the dataset's own is the faithful choice)")
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  data = storage.open_dataset(args.data, args.split)
  if len(data) < args.batch:
    raise ValueError(f"the {args.split} split has {len(data)} objects, fewer than --batch")
  b = data.take(np.arange(args.batch), keys=("trajectories", "primitives", "depth"))
  true = bottom_to_top(jax.tree.map(jnp.asarray, b["primitives"]))
  start = true.replace(density=true.density * 1.3)
  logits = jnp.zeros(true.density.shape + (NUM_DENSITY_SLOTS,))
  traj = jnp.asarray(b["trajectories"], jnp.float32)
  depth = jnp.asarray(b["depth"], jnp.float32)
  d0, m0 = jnp.full((args.batch,), jnp.inf), jnp.zeros((args.batch,))
  common = dict(steps=12, prior_weight=0.0, pushes=default_pushes(), settings=settings_for(args.backend))
  refine = jax.jit(functools.partial(refine_batch, **common))
  runs = {"+Refine (densities)": functools.partial(refine, start, logits, traj, d0, m0)}
  for n in [int(x) for x in args.at_once.split(",")]:
    fn = jax.jit(functools.partial(joint_batch, camera=data.camera, at_once=n, **common))
    runs[f"+Joint (faces, densities, depth), {n} at once"] = functools.partial(
        fn, start, logits, traj, depth, true)
  rows = []
  for name, fn in runs.items():
    first, s = timed(fn, args.repeats)
    rows.append({"run": name, "objects": args.batch, "first_call_s": first, "seconds": s})
    print(f"{name:48s} first {first:7.1f} s  warm {s:7.2f} s", flush=True)
  peer = rows[0]["seconds"]
  print(f"\n{jax.devices()[0].device_kind}, batch of {args.batch} objects, 12 LM passes\n")
  print("| run | warm s / batch | first call s | × +Refine |\n|---|--:|--:|--:|")
  for r in rows:
    print(f"| {r['run']} | {r['seconds']:.2f} | {r['first_call_s']:.1f} | "
          f"{r['seconds'] / peer:.2f} |")
  if args.out:
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
      json.dump({"device": jax.devices()[0].device_kind, "batch": args.batch,
                 "backend": args.backend, "rows": rows},
                f, indent=1)


if __name__ == "__main__":
  main()
