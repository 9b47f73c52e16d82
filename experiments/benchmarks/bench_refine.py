"""The refinements' cost beside +Refine's (the peer) on one batch of objects, in one process.

  python experiments/benchmarks/bench_refine.py --data=DATA --batch=64 --out=FILE.json
  python experiments/benchmarks/bench_refine.py --towers=SEED --backend=box_plane --at_once= \
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

import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

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

flags.DEFINE_string("data", "", "A dataset (or --towers).")
flags.DEFINE_integer("towers", None, "Instead of --data: fresh towers of this seed.")
flags.DEFINE_integer("image_size", 224, "--towers' depth images.")
flags.DEFINE_string("split", "test", "The dataset's split.")
flags.DEFINE_integer("batch", 64, "Objects timed.")
flags.DEFINE_string("at_once", "8,64", "+Joint group sizes to time ('': none).")
flags.DEFINE_string("jacobians", "forward", "Comma-separated +Refine Jacobians (forward, "
                    "differences, central).")
flags.DEFINE_integer("repeats", 3, "Warm calls timed (median).")
flags.DEFINE_enum("backend", "mjx", ["mjx", "box_plane"], "The engine (the dataset's own is the "
                  "faithful choice).")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
FLAGS = flags.FLAGS


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


def main(argv):
  del argv
  settings = settings_for(FLAGS.backend)
  if FLAGS.towers is not None:
    true = bottom_to_top(jax.tree.map(jnp.asarray, ppdjax.sample_towers(FLAGS.towers, FLAGS.batch)))
    camera = camera_dict(FLAGS.image_size, FLAGS.image_size)
    traj = rollout_mjx.simulate(true, default_pushes(), settings=settings)
    depth = render_depths(true, camera)
    source = f"{FLAGS.batch} fresh towers of seed {FLAGS.towers}"
  else:
    if not FLAGS.data:
      raise ValueError("give --data=DIR or --towers=SEED")
    data = storage.open_dataset(FLAGS.data, FLAGS.split)
    if len(data) < FLAGS.batch:
      raise ValueError(f"the {FLAGS.split} split has {len(data)} objects, fewer than --batch")
    b = data.take(np.arange(FLAGS.batch), keys=("trajectories", "primitives", "depth"))
    true = bottom_to_top(jax.tree.map(jnp.asarray, b["primitives"]))
    traj = jnp.asarray(b["trajectories"], jnp.float32)
    depth = jnp.asarray(b["depth"], jnp.float32)
    camera = data.camera
    source = f"the first {FLAGS.batch} objects of {FLAGS.data} ({FLAGS.split})"
  start = true.replace(density=true.density * 1.3)
  logits = jnp.zeros(true.density.shape + (NUM_DENSITY_SLOTS,))
  d0, m0 = jnp.full((FLAGS.batch,), jnp.inf), jnp.zeros((FLAGS.batch,))
  common = dict(steps=12, prior_weight=0.0, pushes=default_pushes(), settings=settings)
  runs = {}
  for jacobian in filter(None, FLAGS.jacobians.split(",")):
    refine = jax.jit(functools.partial(refine_batch, jacobian=jacobian, **common))
    runs[f"+Refine (densities; {jacobian})"] = functools.partial(
        refine, start, logits, traj, d0, m0)
  for n in [int(x) for x in filter(None, FLAGS.at_once.split(","))]:
    fn = jax.jit(functools.partial(joint_batch, camera=camera, at_once=n, **common))
    runs[f"+Joint (faces, densities, depth), {n} at once"] = functools.partial(
        fn, start, logits, traj, depth, true)
  rows = []
  valid = np.asarray(true.valid)
  true_density = np.asarray(true.density)
  for name, fn in runs.items():
    first, s = timed(fn, FLAGS.repeats)
    row = {"run": name, "objects": FLAGS.batch, "first_call_s": first, "seconds": s}
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
        f"12 LM passes, {FLAGS.backend} engine\n")
  print(f"| run | warm s / batch | first call s | × {rows[0]['run']} | boxes within 5 % | "
        "top-1 (%) | RMSE (slots) | MAE (mm) |\n|---|--:|--:|--:|--:|--:|--:|--:|")
  for r in rows:
    acc = "– | – | – | –"
    if "rmse_slots" in r:
      acc = (f"{100 * r['within_5_percent']:.1f} | {r['top1_percent']:.1f} | "
             f"{r['rmse_slots']:.2f} | {r['mae_mm']:.2f}")
    print(f"| {r['run']} | {r['seconds']:.2f} | {r['first_call_s']:.1f} | "
          f"{r['seconds'] / peer:.2f} | {acc} |")
  if FLAGS.out:
    os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
    with open(FLAGS.out, "w") as f:
      json.dump({"device": jax.devices()[0].device_kind, "batch": FLAGS.batch,
                 "source": source, "backend": FLAGS.backend, "rows": rows},
                f, indent=1)


if __name__ == "__main__":
  app.run(main)
