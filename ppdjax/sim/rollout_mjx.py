"""Batched, jitted rollouts: one compiled function serves every object of up to K boxes.

The settings' type picks the engine: `MjxSettings` runs MJX (`mjx.step` or
`ppdjax.sim.mjx_step`), `BoxPlaneSettings` the step written for this scene
(`ppdjax.sim.box_plane`), `MujocoSettings` MuJoCo's C engine through a host callback (the
CPU engine). `engine_settings` picks one for a simulator choice and a backend.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from ppdjax.conventions import STEPS
from ppdjax.primitives import Primitives, flatten, unflatten
from ppdjax.sim import box_plane, box_plane_kernel, mjx_step, rollout_mujoco, scene
from ppdjax.sim.box_plane import BoxPlaneSettings
from ppdjax.sim.rollout_mujoco import MujocoSettings
from ppdjax.sim.mass import mass_properties
from ppdjax.sim.pushes import Pushes, push_wrenches


@dataclasses.dataclass(frozen=True)
class MjxSettings:
  """Solver and loop settings of the MJX backend (see docs/physics.md for measurements).

  Attributes:
    iterations: Newton iterations per step (MuJoCo's default is 100).
    ls_iterations: line-search iterations per Newton iteration (default 50).
    unroll: `jax.lax.scan` unroll over time steps.
    max_contact_points: keep only this many deepest contacts (-1: all 4 per box).
    push_steps_extra: steps after the push that also use the push solver settings.
    push_iterations, push_ls_iterations: solver settings while a push acts (and for
      `push_steps_extra` steps after it): a 1e5 N push changes the contact state in one
      step, which a few Newton iterations do not resolve; the loop stops at convergence.
    fixed_iterations: step with `ppdjax.sim.mjx_step` (the same Newton iterations without
      MJX's while_loop and its host sync per iteration) instead of `mjx.step`; the push
      step too when `push_iterations <= MAX_UNROLLED_ITERATIONS`.
    unrolled_cholesky: with `fixed_iterations`, solve each Newton system by an unrolled
      6x6 Cholesky instead of `jax.scipy.linalg.cho_factor`/`cho_solve`.
  """

  iterations: int = 3
  ls_iterations: int = 2
  unroll: int = 1
  max_contact_points: int = 8
  push_steps_extra: int = 0
  push_iterations: int = 8
  push_ls_iterations: int = 4
  fixed_iterations: bool = True
  unrolled_cholesky: bool = True


DEFAULT_SETTINGS = MjxSettings()
Settings = MjxSettings | BoxPlaneSettings | MujocoSettings
SIMULATORS = ("auto", "jax", "mujoco")

# A candidate far lighter than the object it explains can be launched by the push (a
# 1,000 N tool push sends 0.1 kg flying at 30 m/s), then spin until float32 integration
# diverges. Such a rollout has left the scene: from the first step that is farther than
# this from the origin, or not finite, it keeps its last pose inside (docs/physics.md).
ESCAPE_DISTANCE = 10.0  # m; objects span 1 m, observed tools travel up to 3 m


def hold_escapes(traj: jax.Array) -> jax.Array:
  """(..., T, 7) poses with each rollout held at its last pose within ESCAPE_DISTANCE
  from the first step that leaves it or is not finite. If the first step already does
  (the push alone throws it out), the rollout holds that pose brought back onto the
  sphere of radius ESCAPE_DISTANCE (a non-finite quaternion becomes the identity)."""
  pos = jnp.nan_to_num(traj[..., :3], posinf=0.0, neginf=0.0)
  r2 = jnp.sum(jnp.square(pos), -1)
  inside = jnp.all(jnp.isfinite(traj), -1) & (r2 <= ESCAPE_DISTANCE ** 2)
  inside = jnp.cumprod(inside, -1).astype(bool)
  last = jnp.maximum(jnp.sum(inside, -1) - 1, 0)[..., None, None]
  held_pos = jnp.take_along_axis(pos, last, -2)
  held_pos = held_pos * jnp.minimum(
      1.0, ESCAPE_DISTANCE / jnp.sqrt(jnp.sum(jnp.square(held_pos), -1, keepdims=True)
                                      + 1e-12))
  held_quat = jnp.take_along_axis(traj[..., 3:], last, -2)
  held_quat = jnp.where(jnp.all(jnp.isfinite(held_quat), -1, keepdims=True), held_quat,
                        jnp.array([1.0, 0.0, 0.0, 0.0], traj.dtype))
  return jnp.where(inside[..., None], traj, jnp.concatenate([held_pos, held_quat], -1))


def settings_for(backend: str) -> Settings:
  """The JAX engine's default settings for data simulated by `backend`: the box-plane
  step for "box_plane", MJX otherwise (data made by MuJoCo C is read through MJX)."""
  return BoxPlaneSettings() if backend == "box_plane" else DEFAULT_SETTINGS


def check_simulator(simulator: str) -> str:
  """`simulator` if it is one of SIMULATORS, else ValueError."""
  if simulator not in SIMULATORS:
    raise ValueError(f"simulator must be one of {SIMULATORS}, got {simulator!r}")
  return simulator


def engine_settings(simulator: str, data_engine: str | Settings) -> Settings:
  """The engine that simulates the candidates of `decompose`'s selection (and the
  evaluation's).

  Args:
    simulator: "jax": the JAX engine of the data (`settings_for(data_engine)`), the GPU
      engine; "mujoco": MuJoCo's C engine on every CPU core (`MujocoSettings`); "auto":
      C where JAX runs on a CPU, else JAX.
    data_engine: the engine the observations come from ("mjx", "box_plane", "mujoco") or
      the JAX engine's settings themselves.
  """
  check_simulator(simulator)
  if simulator == "mujoco" or (simulator == "auto" and jax.default_backend() == "cpu"):
    return MujocoSettings()
  return jax_engine(data_engine)


def jax_engine(data_engine: str | Settings) -> Settings:
  """The JAX engine for data from `data_engine` (a name, or settings kept as they are;
  data from MuJoCo C is read through MJX): the engine refinement differentiates."""
  settings = settings_for(data_engine) if isinstance(data_engine, str) else data_engine
  return DEFAULT_SETTINGS if isinstance(settings, MujocoSettings) else settings


# Above this many push iterations the push step keeps MJX's while_loop (unrolling 100
# iterations would take minutes to compile).
MAX_UNROLLED_ITERATIONS = 16


@functools.lru_cache(maxsize=8)
def template(settings: MjxSettings = DEFAULT_SETTINGS, num_slots: int = 5, push: bool = False):
  """The MJX template model with the solver settings (of the push steps if `push`)."""
  xml = scene.scene_xml(num_slots=num_slots)
  if settings.max_contact_points > 0:
    xml = xml.replace("</mujoco>", '  <custom><numeric name="max_contact_points" data="'
                      f'{settings.max_contact_points}"/></custom>\n</mujoco>')
  model = mujoco.MjModel.from_xml_string(xml)
  model.opt.iterations = settings.push_iterations if push else settings.iterations
  model.opt.ls_iterations = settings.push_ls_iterations if push else settings.ls_iterations
  with jax.ensure_compile_time_eval():  # concrete arrays, even when first called under jit
    return mjx.put_model(model)


def with_object(mx, fields: dict[str, jax.Array]):
  """The template model with one object's fields (`scene.object_fields`) written in."""
  k = fields["geom_size"].shape[0]
  geoms = slice(scene.FIRST_BOX_GEOM, scene.FIRST_BOX_GEOM + k)
  updates = {}
  for name, value in fields.items():
    old = getattr(mx, name)
    value = value.astype(old.dtype)
    updates[name] = old.at[geoms].set(value) if name in scene.GEOM_FIELDS else value
  return mx.replace(**updates)


def rollout_object(prims: Primitives, pushes: Pushes, *, steps: int,
                   settings: Settings = DEFAULT_SETTINGS) -> jax.Array:
  """(P, steps, 7) trajectories of one object (K slots) under P pushes; traceable.

  `settings` picks the step: MjxSettings runs MJX, BoxPlaneSettings the box-plane step.
  A rollout that leaves the scene or diverges is held (`hold_escapes`).
  """
  if isinstance(settings, BoxPlaneSettings):
    run = box_plane_kernel.rollout if settings.resolved_kernel() == "pallas" else box_plane.rollout
    return hold_escapes(box_plane.rollout_object(prims, pushes, steps=steps,
                                                 settings=settings, run_rollout=run))
  return _mjx_rollouts(jax.tree.map(lambda x: x[None], prims), pushes, steps, settings)[0]


def _mjx_rollouts(prims: Primitives, pushes: Pushes, steps: int,
                  settings: MjxSettings) -> jax.Array:
  """(B, P, steps, 7) MJX trajectories of B objects, held (`hold_escapes`): one vmap over
  every (object, push) pair, not one over pushes inside one over objects, since each vmap
  level batches the scans' bodies (MJX's whole step) once more (docs/physics.md)."""
  wrenches = jax.vmap(lambda p: push_wrenches(p, pushes, mass_properties(p)))(prims)
  b, p = wrenches.shape[:2]
  pairs = jax.tree.map(lambda x: jnp.repeat(x, p, axis=0), prims)
  traj = jax.vmap(lambda q, w: _mjx_rollout(q, w, pushes.duration, steps, settings))(
      pairs, wrenches.reshape(b * p, 6))
  return hold_escapes(traj.reshape((b, p) + traj.shape[1:]))


def _mjx_rollout(prims: Primitives, wrench: jax.Array, duration: int, steps: int,
                 settings: MjxSettings) -> jax.Array:
  """(steps, 7) MJX trajectory of one object (K slots) under one push's wrench (6,), held
  for `duration` steps; the push steps (and `push_steps_extra` after) with the push's
  solver settings."""
  k = prims.density.shape[-1]
  mx = template(settings, k)
  fields = scene.object_fields(prims)
  m_fast, m_push = with_object(mx, fields), with_object(template(settings, k, push=True), fields)
  qpos0 = jnp.concatenate([scene.rest_position(prims), jnp.array([1.0, 0.0, 0.0, 0.0])])
  d0 = mjx.make_data(mx).replace(qpos=qpos0.astype(jnp.float32))
  n_push = min(steps, duration + settings.push_steps_extra)
  xfrc = jnp.zeros((mx.nbody, 6), jnp.float32).at[scene.OBJECT_BODY].set(wrench)

  def stepper(m, step_fn):
    def step(d, t):
      d = d.replace(xfrc_applied=jnp.where(t < duration, xfrc, 0.0))
      d = step_fn(m, d)
      return d, d.qpos[:7]
    return step

  push_step = fast_step = mjx.step
  if settings.fixed_iterations:
    fast_step = functools.partial(mjx_step.step, iterations=settings.iterations,
                                  unrolled_cholesky=settings.unrolled_cholesky)
    if settings.push_iterations <= MAX_UNROLLED_ITERATIONS:
      push_step = functools.partial(mjx_step.step, iterations=settings.push_iterations,
                                    unrolled_cholesky=settings.unrolled_cholesky)
  d, traj_push = jax.lax.scan(stepper(m_push, push_step), d0, jnp.arange(n_push))
  _, traj = jax.lax.scan(stepper(m_fast, fast_step), d, jnp.arange(n_push, steps),
                         unroll=settings.unroll)
  return jnp.concatenate([traj_push, traj], 0)


@functools.lru_cache(maxsize=16)
def _batched_fn(steps: int, settings: Settings):
  def run(prims, pushes):
    if isinstance(settings, MjxSettings):
      return _mjx_rollouts(prims, pushes, steps, settings)
    return jax.vmap(lambda p: rollout_object(p, pushes, steps=steps, settings=settings))(prims)
  return jax.jit(run)


def simulate(prims: Primitives, pushes: Pushes, *, steps: int = STEPS,
             settings: Settings = DEFAULT_SETTINGS) -> jax.Array:
  """(B..., P, steps, 7) float32 trajectories; one jitted call for the whole batch."""
  flat, batch = flatten(jax.tree.map(jnp.asarray, prims))
  flat = flat.replace(half_size=flat.half_size.astype(jnp.float32),
                      pos=flat.pos.astype(jnp.float32), quat=flat.quat.astype(jnp.float32),
                      density=flat.density.astype(jnp.float32),
                      valid=flat.valid.astype(bool))
  if flat.inertia_scale is not None:
    flat = flat.replace(inertia_scale=flat.inertia_scale.astype(jnp.float32))
  if isinstance(settings, MujocoSettings):
    out = hold_escapes(rollout_mujoco.simulate_traced(flat, pushes, steps=steps,
                                                      settings=settings))
  else:
    out = _batched_fn(steps, settings)(flat, pushes.float32())
  return unflatten(out, batch)
