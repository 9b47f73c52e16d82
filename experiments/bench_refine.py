"""The refinements' cost beside +Refine's (the peer) on one batch of objects, in one process.

  python experiments/bench_refine.py --data=DATA --batch=64 --out=FILE.json
  python experiments/bench_refine.py --towers=SEED --backend=box_plane --at_once= \
      --jacobians=forward,differences --out=FILE.json

Takes the first --batch objects of a split (their true boxes, densities 30 % off, the
depth image and its camera), or with --towers that many fresh towers of a seed observed
by the --backend engine (depth ray-cast from the datasets' camera), and times, warm, the
evaluation's refinements as it runs them: `refine.refine_batch` (densities alone, 12 LM
passes, the Jacobian by each of --jacobians: forward mode with K tangents, or forward
differences, K + 1 rollouts in one call, `refine.difference_jacobian`) and
`joint.joint_batch` (faces and densities, 7K tangents, the depth image too) with
--at_once objects per vectorised group (the evaluation uses 64 on an accelerator, 8 on a
CPU). Cost depends on the shapes and iteration count, not on the start. Prints a markdown
table with the ratio to the first run and, for the density refinements, how close each
lands to the true densities.
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

import ppdjax
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset import storage
from ppdjax.dataset.camera import camera_dict
from ppdjax.dataset.depth import render_depths
from ppdjax.infer.joint import joint_batch
from ppdjax.infer.refine import refine_batch
from ppdjax.primitives import bottom_to_top
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim import rollout_mjx
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
  parser.add_argument("--data", default="", help="a dataset (or --towers)")
  parser.add_argument("--towers", type=int, default=None,
                      help="instead of --data: fresh towers of this seed")
  parser.add_argument("--image_size", type=int, default=224, help="--towers' depth images")
  parser.add_argument("--split", default="test")
  parser.add_argument("--batch", type=int, default=64)
  parser.add_argument("--at_once", default="8,64", help="+Joint group sizes to time ('': none)")
  parser.add_argument("--jacobians", default="forward",
                      help="comma-separated +Refine Jacobians (forward, differences, central)")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--backend", default="mjx", choices=("mjx", "box_plane"),
                      help="the engine (the dataset's own is the faithful choice)")
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  settings = settings_for(args.backend)
  if args.towers is not None:
    true = bottom_to_top(jax.tree.map(jnp.asarray, ppdjax.sample_towers(args.towers, args.batch)))
    camera = camera_dict(args.image_size, args.image_size)
    traj = rollout_mjx.simulate(true, default_pushes(), settings=settings)
    depth = render_depths(true, camera)
    source = f"{args.batch} fresh towers of seed {args.towers}"
  else:
    if not args.data:
      raise ValueError("give --data=DIR or --towers=SEED")
    data = storage.open_dataset(args.data, args.split)
    if len(data) < args.batch:
      raise ValueError(f"the {args.split} split has {len(data)} objects, fewer than --batch")
    b = data.take(np.arange(args.batch), keys=("trajectories", "primitives", "depth"))
    true = bottom_to_top(jax.tree.map(jnp.asarray, b["primitives"]))
    traj = jnp.asarray(b["trajectories"], jnp.float32)
    depth = jnp.asarray(b["depth"], jnp.float32)
    camera = data.camera
    source = f"the first {args.batch} objects of {args.data} ({args.split})"
  start = true.replace(density=true.density * 1.3)
  logits = jnp.zeros(true.density.shape + (NUM_DENSITY_SLOTS,))
  d0, m0 = jnp.full((args.batch,), jnp.inf), jnp.zeros((args.batch,))
  common = dict(steps=12, prior_weight=0.0, pushes=default_pushes(), settings=settings)
  runs = {}
  for jacobian in filter(None, args.jacobians.split(",")):
    refine = jax.jit(functools.partial(refine_batch, jacobian=jacobian, **common))
    runs[f"+Refine (densities; {jacobian})"] = functools.partial(
        refine, start, logits, traj, d0, m0)
  for n in [int(x) for x in filter(None, args.at_once.split(","))]:
    fn = jax.jit(functools.partial(joint_batch, camera=camera, at_once=n, **common))
    runs[f"+Joint (faces, densities, depth), {n} at once"] = functools.partial(
        fn, start, logits, traj, depth, true)
  rows = []
  valid = np.asarray(true.valid)
  true_density = np.asarray(true.density)
  for name, fn in runs.items():
    first, s = timed(fn, args.repeats)
    row = {"run": name, "objects": args.batch, "first_call_s": first, "seconds": s}
    if name.startswith("+Refine"):  # where the densities land (the start: 30 % off)
      out = jax.device_get(fn())
      slots = np.rint(out["density"] / 100.0) - np.rint(true_density / 100.0)
      rel = np.abs(out["density"] / np.where(valid, true_density, 1.0) - 1.0)
      row.update({"within_5_percent": float((rel < 0.05)[valid].mean()),
                  "rmse_slots": float(np.sqrt((slots[valid] ** 2).mean())),
                  "top1_percent": float(100 * (slots[valid] == 0).mean()),
                  "mae_mm": float(np.mean(out["mae"]))})
    rows.append(row)
    print(f"{name:48s} first {first:7.1f} s  warm {s:7.2f} s", flush=True)
  peer = rows[0]["seconds"]
  print(f"\n{jax.devices()[0].device_kind}, {source}, true boxes with densities 30 % off, "
        f"12 LM passes, {args.backend} engine\n")
  print(f"| run | warm s / batch | first call s | × {rows[0]['run']} | boxes within 5 % | "
        "top-1 (%) | RMSE (slots) | MAE (mm) |\n|---|--:|--:|--:|--:|--:|--:|--:|")
  for r in rows:
    acc = "– | – | – | –"
    if "rmse_slots" in r:
      acc = (f"{100 * r['within_5_percent']:.1f} | {r['top1_percent']:.1f} | "
             f"{r['rmse_slots']:.2f} | {r['mae_mm']:.2f}")
    print(f"| {r['run']} | {r['seconds']:.2f} | {r['first_call_s']:.1f} | "
          f"{r['seconds'] / peer:.2f} | {acc} |")
  if args.out:
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
      json.dump({"device": jax.devices()[0].device_kind, "batch": args.batch,
                 "source": source, "backend": args.backend, "rows": rows},
                f, indent=1)


if __name__ == "__main__":
  main()
