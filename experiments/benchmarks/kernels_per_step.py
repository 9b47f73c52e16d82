"""Where a step's time goes: kernels per simulation step, MJX beside the box-plane step.

  python experiments/benchmarks/kernels_per_step.py --rollouts 2048

Compiles one vmapped step of each engine (the steps after the push, package defaults) for
--rollouts random tower rollouts and counts, in the optimised HLO, the instructions that
launch work on the device (fusions, custom calls, sorts, copies, ...), per computation:
a step's launches are the entry's plus each loop body's times its trip count (MJX's line
search is a `scan`). Also times the step alone (a warm jitted call, which adds one
dispatch). Prints a markdown table.
"""

from __future__ import annotations

import re
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from mujoco import mjx

import ppdjax
from ppdjax.primitives import flatten
from ppdjax.sim import box_plane, mjx_step, rollout_mjx, scene

LAUNCHES = re.compile(r"=\s*\S+\s+(fusion|custom-call|sort|copy|reduce|scatter|gather|dot|"
                      r"convolution|all-reduce|transpose|dynamic-update-slice)\(")

flags.DEFINE_integer("rollouts", 2048, "Random tower rollouts in the vmapped step.")
FLAGS = flags.FLAGS


def launches(hlo: str) -> dict[str, int]:
  """Launching instructions of the entry and of each while-loop body of an optimised HLO
  module (fused computations and reduction regions run inside those launches)."""
  counts, name = {}, None
  for line in hlo.splitlines():
    head = re.match(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
    if head:
      name = "ENTRY" if head.group(1) else head.group(2)
      if name == "ENTRY" or "body" in name:
        counts[name] = 0
    elif name in counts and LAUNCHES.search(line):
      counts[name] += 1
  return counts


def timed(fn, *args, repeats=20):
  jax.block_until_ready(fn(*args))
  t = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    t.append(time.perf_counter() - t0)
  return float(np.median(t))


def main(argv):
  del argv
  prims, _ = flatten(jax.tree.map(jnp.asarray, ppdjax.sample_towers(0, FLAGS.rollouts)))
  prims = jax.tree.map(lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, prims)
  wrench = jnp.zeros((FLAGS.rollouts, 6), jnp.float32)

  bp = box_plane.BoxPlaneSettings()
  def bp_state(p):
    qpos = jnp.concatenate([scene.rest_position(p), jnp.array([1.0, 0, 0, 0])])
    return box_plane.body_of(p), box_plane.State(qpos, jnp.zeros(6), jnp.zeros(6))
  bodies, states = jax.vmap(bp_state)(prims)
  bp_step = jax.jit(jax.vmap(lambda b, s, w: box_plane.step(
      b, s, w, iterations=bp.iterations, ls_iterations=bp.ls_iterations,
      max_contacts=bp.max_contacts)))

  mj = rollout_mjx.MjxSettings()
  mx = rollout_mjx.template(mj)
  def mjx_data(p):
    m = rollout_mjx.with_object(mx, scene.object_fields(p))
    qpos = jnp.concatenate([scene.rest_position(p), jnp.array([1.0, 0, 0, 0])])
    return m, mjx.make_data(mx).replace(qpos=qpos.astype(jnp.float32))
  models, datas = jax.vmap(mjx_data)(prims)
  mjx_fn = jax.jit(jax.vmap(lambda m, d: mjx_step.step(
      m, d, iterations=mj.iterations, unrolled_cholesky=mj.unrolled_cholesky)))

  print("| engine | launches in the entry | loop bodies (launches) | step alone (ms) |")
  print("|---|--:|---|--:|")
  for name, fn, fargs in (("MJX (package default)", mjx_fn, (models, datas)),
                          ("box-plane step (default)", bp_step, (bodies, states, wrench))):
    counts = launches(fn.lower(*fargs).compile().as_text())
    entry = counts.pop("ENTRY")
    bodies_ = ", ".join(f"{v}" for v in counts.values()) or "none"
    print(f"| {name} | {entry} | {bodies_} | {timed(fn, *fargs) * 1e3:.3f} |", flush=True)


if __name__ == "__main__":
  app.run(main)
