"""Rollouts in MuJoCo's C engine (`mujoco.batch`, all CPU cores): the reference backend, and
the CPU engine of `decompose` (`MujocoSettings`: called from inside `jax.jit`)."""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import mujoco
from mujoco import batch as mj_batch

from ppdjax.conventions import STEPS
from ppdjax.primitives import Primitives, flatten
from ppdjax.sim import scene
from ppdjax.sim.pushes import Pushes, push_wrenches

# Fields written per simulation; mj_setConst then derives invweight0, meaninertia etc.
_WRITTEN = ("geom_size", "geom_pos", "geom_quat", "geom_rbound", "geom_aabb", "body_mass",
            "body_ipos", "body_iquat", "body_inertia")


_TIME = int(mujoco.mjtState.mjSTATE_TIME)  # recorded beside qpos: a stopped rollout's clock stops


@dataclasses.dataclass(frozen=True)
class MujocoSettings:
  """MuJoCo's C engine inside a jitted function: each batch of rollouts leaves the program
  for the host (`jax.pure_callback`), runs on `nthread` CPU threads and comes back as
  float32. On a CPU it is the fast engine (docs/physics.md: 10x MJX and 5x the box-plane
  step on 2 cores); it has no derivatives (+Refine by differences runs it, forward mode
  does not).

  Attributes:
    nthread: threads of `mujoco.batch` (0: every CPU).
    iterations, ls_iterations: solver overrides (None: MuJoCo's defaults, 100 and 50;
      Newton stops at convergence, a few iterations on these scenes).
  """

  nthread: int = 0
  iterations: int | None = None
  ls_iterations: int | None = None


def object_inputs(prims: Primitives, pushes: Pushes):
  """What C needs of one object (K slots), computed in JAX (traceable): its model fields
  (`scene.object_fields`), its P push wrenches and its rest position."""
  fields = {k: v for k, v in scene.object_fields(prims).items() if k in _WRITTEN}
  return fields, push_wrenches(prims, pushes), scene.rest_position(prims)


_batched_inputs = jax.jit(jax.vmap(object_inputs, in_axes=(0, None)))


class UnstableRollout(RuntimeError):
  """MuJoCo stopped a rollout on a warning (its solver met a NaN, an infinite or a huge
  acceleration): the trajectory after that step is not physics."""


def run_inputs(fields: dict, wrenches_NxPx6: np.ndarray, rest_Nx3: np.ndarray, *,
               steps: int, duration: int, settings: MujocoSettings = MujocoSettings(),
               stopped: list | None = None) -> np.ndarray:
  """(N, P, steps, 7) float64 trajectories of N objects (`object_inputs`, stacked) under
  their P pushes, each acting for its first `duration` steps. `stopped`: a list that gets
  the (N, P) int array of the step at which MuJoCo stopped each rollout on a warning (-1:
  it ran to the end)."""
  n, p = wrenches_NxPx6.shape[:2]
  k = fields["geom_size"].shape[1]
  model = copy.copy(scene.template_model(k))
  if settings.iterations is not None:
    model.opt.iterations = settings.iterations
  if settings.ls_iterations is not None:
    model.opt.ls_iterations = settings.ls_iterations
  sims = mj_batch.Batch(model, nsim=n * p, nthread=settings.nthread)
  geoms = slice(scene.FIRST_BOX_GEOM, scene.FIRST_BOX_GEOM + k)
  for name, value in fields.items():
    value = np.repeat(np.asarray(value, np.float64), p, axis=0)  # sim = object * P + push
    target = sims.expand(name)
    if name in scene.GEOM_FIELDS:
      target[:, geoms] = value
    else:
      target[:] = value
  sims.set_const()
  sims.reset()
  qpos = sims.bind("qpos")
  qpos[:, :3] = np.repeat(rest_Nx3, p, axis=0)
  qpos[:, 3:7] = [1.0, 0.0, 0.0, 0.0]
  sims.bind("qvel")[:] = 0.0
  xfrc = sims.bind("xfrc_applied")
  xfrc[:] = 0.0
  xfrc[:, scene.OBJECT_BODY] = np.asarray(wrenches_NxPx6).reshape(n * p, 6)
  first = min(duration, steps)
  # a simulation whose warnings rise (a diverging candidate) stops and repeats its last
  # pose, as the JAX engines hold an escaped rollout (`rollout_mjx.hold_escapes`)
  # (its clock stops with it: the recorded time tells which stopped, and where)
  record = ("qpos",) if stopped is None else ("qpos", _TIME)
  parts = [sims.rollout(first, record=record)]
  xfrc[:] = 0.0
  if steps > first:
    parts.append(sims.rollout(steps - first, record=record))
  if stopped is not None:
    time = np.concatenate([r[_TIME][..., 0] for r in parts], axis=1)  # (N P, steps)
    ran = np.round(time / model.opt.timestep).astype(np.int64)
    late = ran < np.arange(1, steps + 1)
    stopped.append(np.where(late.any(1), np.argmax(late, 1), -1).reshape(n, p))
  return np.concatenate([r["qpos"] for r in parts], axis=1)[..., :7].reshape(n, p, steps, 7)


def simulate(prims: Primitives, pushes: Pushes, *, steps: int = STEPS, nthread: int = 0,
             iterations: int | None = None, ls_iterations: int | None = None) -> np.ndarray:
  """(B..., P, steps, 7) float64 trajectories from MuJoCo C.

  Args:
    prims: concrete Primitives with batch axes B...
    pushes: the pushes.
    steps: recorded steps.
    nthread: threads for `mujoco.batch` (0: all CPUs).
    iterations, ls_iterations: solver overrides (None: MuJoCo's defaults, 100 and 50).

  Raises:
    UnstableRollout: naming the object, the push and the step where MuJoCo stopped a
      rollout on a warning (a diverging simulation; `simulate` documents the densities
      the engines are stable for).
  """
  flat, batch = flatten(jax.tree.map(np.asarray, prims))
  fields, wrenches, rest = jax.tree.map(np.asarray, _batched_inputs(
      jax.tree.map(jnp.asarray, flat), pushes.float32()))
  stopped = []
  traj = run_inputs(fields, wrenches, rest, steps=steps, duration=pushes.duration,
                    settings=MujocoSettings(nthread, iterations, ls_iterations),
                    stopped=stopped)
  bad = np.argwhere(stopped[0] >= 0)
  if len(bad):
    i, push = bad[0]
    where = np.unravel_index(i, batch) if batch else ()
    raise UnstableRollout(
        f"MuJoCo's C engine became unstable (a NaN, infinite or huge acceleration) and "
        f"stopped {len(bad)} of {stopped[0].size} rollouts; the first: object "
        f"{tuple(int(x) for x in where)} under push {int(push)} at step "
        f"{int(stopped[0][i, push])} (its boxes' densities "
        f"{flat.density[i][flat.valid[i]].round(1).tolist()} kg/m^3)")
  return traj.reshape(batch + (pushes.num, steps, 7))


def simulate_traced(prims: Primitives, pushes: Pushes, *, steps: int,
                    settings: MujocoSettings) -> jax.Array:
  """(N, P, steps, 7) float32 trajectories of N objects (N, K) from MuJoCo C, callable
  inside `jax.jit` and under `jax.vmap` (every vmapped call becomes one batch on the host:
  all cores at once). The pushes' arrays may be traced (each object's own magnitudes):
  their wrenches are computed in JAX before the host call."""
  n, p = prims.density.shape[0], pushes.num
  inputs = jax.vmap(object_inputs, in_axes=(0, None))(prims, pushes.float32())

  def host(fields, wrenches, rest):
    lead = rest.shape[:-1]  # (V..., N): the vmapped axes, then the objects
    fields = {k: np.reshape(v, (-1,) + v.shape[len(lead):]) for k, v in fields.items()}
    traj = run_inputs(fields, np.reshape(wrenches, (-1, p, 6)), np.reshape(rest, (-1, 3)),
                      steps=steps, duration=pushes.duration, settings=settings)
    return traj.astype(np.float32).reshape(lead + (p, steps, 7))

  return jax.pure_callback(host, jax.ShapeDtypeStruct((n, p, steps, 7), jnp.float32),
                           *inputs, vmap_method="broadcast_all")
