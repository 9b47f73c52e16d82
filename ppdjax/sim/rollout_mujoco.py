"""Rollouts in MuJoCo's C engine (`mujoco.batch`, all CPU cores): the reference backend."""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import batch as mj_batch

from ppdjax.conventions import STEPS
from ppdjax.primitives import Primitives, flatten
from ppdjax.sim import scene
from ppdjax.sim.pushes import Pushes, push_wrenches

# Fields written per simulation; mj_setConst then derives invweight0, meaninertia etc.
_WRITTEN = ("geom_size", "geom_pos", "geom_quat", "geom_rbound", "geom_aabb", "body_mass",
            "body_ipos", "body_iquat", "body_inertia")


@jax.jit
def _object_inputs(prims: Primitives, pushes: Pushes):
  def one(p):
    fields = {k: v for k, v in scene.object_fields(p).items() if k in _WRITTEN}
    return fields, push_wrenches(p, pushes), scene.rest_position(p)
  return jax.vmap(one)(prims)


def simulate(prims: Primitives, pushes: Pushes, *, steps: int = STEPS, nthread: int = 0,
             iterations: int | None = None, ls_iterations: int | None = None) -> np.ndarray:
  """(B..., P, steps, 7) float64 trajectories from MuJoCo C.

  Args:
    prims: concrete Primitives with batch axes B...
    pushes: the pushes.
    steps: recorded steps.
    nthread: threads for `mujoco.batch` (0: all CPUs).
    iterations, ls_iterations: solver overrides (None: MuJoCo's defaults, 100 and 50).
  """
  flat, batch = flatten(jax.tree.map(np.asarray, prims))
  k = flat.num_slots
  n, p = flat.density.shape[0], pushes.num
  fields, wrenches, rest = jax.tree.map(np.asarray, _object_inputs(
      jax.tree.map(jnp.asarray, flat), pushes.float32()))

  model = copy.copy(scene.template_model(k))
  if iterations is not None:
    model.opt.iterations = iterations
  if ls_iterations is not None:
    model.opt.ls_iterations = ls_iterations
  sims = mj_batch.Batch(model, nsim=n * p, nthread=nthread)
  geoms = slice(scene.FIRST_BOX_GEOM, scene.FIRST_BOX_GEOM + k)
  for name, value in fields.items():
    value = np.repeat(value.astype(np.float64), p, axis=0)  # sim index = object * P + push
    target = sims.expand(name)
    if name in scene.GEOM_FIELDS:
      target[:, geoms] = value
    else:
      target[:] = value
  sims.set_const()
  sims.reset()
  qpos = sims.bind("qpos")
  qpos[:, :3] = np.repeat(rest, p, axis=0)
  qpos[:, 3:7] = [1.0, 0.0, 0.0, 0.0]
  sims.bind("qvel")[:] = 0.0
  xfrc = sims.bind("xfrc_applied")
  xfrc[:] = 0.0
  xfrc[:, scene.OBJECT_BODY] = wrenches.reshape(n * p, 6)
  first = min(pushes.duration, steps)
  parts = [sims.rollout(first, record=("qpos",))["qpos"]]
  xfrc[:] = 0.0
  if steps > first:
    parts.append(sims.rollout(steps - first, record=("qpos",))["qpos"])
  traj = np.concatenate(parts, axis=1)[..., :7]
  return traj.reshape(batch + (p, steps, 7))
