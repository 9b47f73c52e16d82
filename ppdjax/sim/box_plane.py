"""A step built for this scene: one free rigid body of up to K boxes on a ground plane.

`ppdjax.sim.mjx_step` runs MJX's general pipeline (kinematic tree scans, convex-mesh
collision, constraint assembly) in many small kernels per step. Here every object is one
free body, so the same physics is a handful of 6x6 and (contacts x 4 edges) x 6 array
expressions (70 kernel launches per step on a GPU, against MJX's 144):

- **Dynamics** of a free joint as MuJoCo defines it: qpos = (origin position, world;
  orientation quaternion), qvel = (origin velocity, world; angular velocity, body axes).
  The mass matrix, gravity, the velocity product terms and `xfrc_applied` (force and
  torque at the centre of mass) are written in closed form.
- **Contacts** by MuJoCo C's box-plane routine (`mjc_PlaneBox`): per box, the corners
  below the box centre that touch the ground (at most 4), each at the corner moved half its
  depth back along the normal; the deepest `max_contacts` of them are kept.
- **Constraints**: MuJoCo's soft contacts with a pyramidal cone (4 edges per contact,
  friction 1, `solref`/`solimp` defaults, `impratio` 1), solved by `ppdjax.sim.newton`
  (MuJoCo's Newton solver as MJX runs it, for a fixed number of iterations).
- **Integration**: semi-implicit Euler, the quaternion by MuJoCo's `mju_quatIntegrate`.

Pure JAX on one rollout; `jax.vmap` batches it. Differentiable in forward mode and, with
its fixed iterations, in reverse mode. The constants below are MuJoCo's defaults, which
the scene's template model uses (tests/test_physics.py pins them, and tests the step
against MuJoCo C and against MJX).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax.conventions import TIMESTEP
from ppdjax.primitives import Primitives, quat_to_mat
from ppdjax.sim.mass import mass_properties
from ppdjax.sim.pushes import Pushes, push_wrenches
from ppdjax.sim.scene import rest_position
from ppdjax.sim import newton
from ppdjax.sim.newton import MINVAL
from ppdjax.sim.small_linalg import cholesky_solve

GRAVITY = np.array([0.0, 0.0, -9.81], np.float32)  # MuJoCo's default
FRICTION = 1.0  # MuJoCo's default sliding friction (condim 3: sliding only)
SOLREF = (0.02, 1.0)  # MuJoCo's default time constant and damping ratio
SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)  # dmin, dmax, width, midpoint, power
KERNELS = ("auto", "reference", "pallas")
CORNER_SIGNS = np.array([[1 if i & 1 else -1, 1 if i & 2 else -1, 1 if i & 4 else -1]
                         for i in range(8)], np.float32)  # mjc_PlaneBox's corner order


@dataclasses.dataclass(frozen=True)
class BoxPlaneSettings:
  """Solver settings of the box-plane step (docs/physics.md has the measurements).

  Attributes:
    iterations, ls_iterations: Newton and line-search iterations of every step after the
      push (and `push_steps_extra` more).
    push_iterations, push_ls_iterations: those of the steps while a push acts: a 1e5 N
      push changes the contact state within one step, which few iterations do not
      resolve; elements stop at convergence.
    push_steps_extra: steps after the push that also use the push settings.
    max_contacts: keep the deepest this many contacts (0: all, 4 per box, as MuJoCo C);
      8 costs no agreement with C on the benchmark towers and halves the rows.
    kernel: "reference" runs this module's step (XLA); "pallas" runs whole rollouts as
      one Pallas kernel (`ppdjax.sim.box_plane_kernel`; interpreted off a GPU), the same
      trajectories to 0.001 mm at p90, 1.67x faster than the XLA step at 2,048
      rollouts on an H100 and, with its launch shape by batch size, 1.69x faster than
      before at 131,072 (benchmarks.md), with a longer first compile (about 100 s against 45 s;
      docs/physics.md); "auto" (the default) is "pallas" on a GPU, else "reference".
      Derivatives always run this module's step (+Refine can take differences through
      the kernel instead: `infer.refine.check_jacobian`).
    kernel_block, kernel_warps: the kernel's launch: rollouts and GPU warps per program
      (0: by the number of rollouts, `box_plane_kernel.launch_shape`, measured on an
      H100); the physics is the same at any.
  """

  iterations: int = 3
  ls_iterations: int = 2
  push_iterations: int = 8
  push_ls_iterations: int = 4
  push_steps_extra: int = 0
  max_contacts: int = 8
  kernel: str = "auto"
  kernel_block: int = 0
  kernel_warps: int = 0

  def __post_init__(self):
    if self.kernel not in KERNELS:
      raise ValueError(f"BoxPlaneSettings.kernel must be one of {KERNELS}, got {self.kernel!r}")
    for name in ("kernel_block", "kernel_warps"):
      n = getattr(self, name)
      if n < 0 or n & (n - 1):
        raise ValueError(f"BoxPlaneSettings.{name} must be 0 or a power of two, got {n}")

  def resolved_kernel(self) -> str:
    """"reference" or "pallas": what "auto" means on the default backend."""
    if self.kernel != "auto":
      return self.kernel
    return "pallas" if jax.default_backend() == "gpu" else "reference"


@struct.dataclass
class Body:
  """What the step needs of one object: mass properties and boxes in the body frame."""

  mass: jax.Array  # ()
  com: jax.Array  # (3,)
  inertia: jax.Array  # (3, 3) about the centre of mass, body axes
  box_pos: jax.Array  # (K, 3)
  box_rot: jax.Array  # (K, 3, 3)
  half_size: jax.Array  # (K, 3)
  valid: jax.Array  # (K,) bool


@struct.dataclass
class State:
  qpos: jax.Array  # (7,) origin position (world), orientation quaternion (w, x, y, z)
  qvel: jax.Array  # (6,) origin velocity (world), angular velocity (body axes)
  qacc_warmstart: jax.Array  # (6,) the last step's acceleration


def body_of(prims: Primitives) -> Body:
  """The Body of one object (K slots); invalid slots never make contacts."""
  props = mass_properties(prims)
  quat = prims.quat / jnp.linalg.norm(prims.quat, axis=-1, keepdims=True)
  return Body(mass=props.mass, com=props.com, inertia=props.inertia, box_pos=prims.pos,
              box_rot=quat_to_mat(quat), half_size=prims.half_size, valid=prims.valid)


def _skew(v: jax.Array) -> jax.Array:
  z = jnp.zeros_like(v[0])
  return jnp.stack([jnp.stack([z, -v[2], v[1]]), jnp.stack([v[2], z, -v[0]]),
                    jnp.stack([-v[1], v[0], z])])


def _mass_matrix(body: Body, rot: jax.Array) -> jax.Array:
  """6x6 joint-space inertia of the free joint (MuJoCo's M)."""
  m, c = body.mass, _skew(body.com)
  top = jnp.concatenate([m * jnp.eye(3), -m * rot @ c], 1)
  bottom = jnp.concatenate([m * c @ rot.T, body.inertia - m * c @ c], 1)
  return jnp.concatenate([top, bottom], 0)


def _smooth_force(body: Body, rot: jax.Array, qvel: jax.Array, wrench: jax.Array) -> jax.Array:
  """Gravity, applied wrench (world force and torque at the centre of mass) minus the
  velocity product terms, in joint space (MuJoCo's qfrc_smooth)."""
  omega_b = qvel[3:]
  omega = rot @ omega_b
  r = rot @ body.com  # origin -> centre of mass, world
  centripetal = body.mass * jnp.cross(omega, jnp.cross(omega, r))
  force = body.mass * GRAVITY + wrench[:3] - centripetal
  torque_b = rot.T @ (jnp.cross(r, force) + wrench[3:])
  gyroscopic = jnp.cross(omega_b, body.inertia @ omega_b)
  return jnp.concatenate([force, torque_b - gyroscopic])


def _contacts(body: Body, qpos: jax.Array, rot: jax.Array, max_contacts: int = 0):
  """Box-plane contacts, 4 corner slots per box: (C,) depth, (C, 3) point, (C,) active.

  Corners come in opposite pairs (i, 7 - i); at most one of each pair lies below the box
  centre, so the 4 slots of a box hold the lower corner of each pair: the same contacts
  as mjc_PlaneBox's "first 4 of the lower corners" except when a corner lies exactly at
  the centre's height (a tie of measure zero, where C may take both of a pair).
  """
  centre = qpos[:3] + body.box_pos @ rot.T  # (K, 3)
  box_rot = jnp.einsum("ij,kjl->kil", rot, body.box_rot)  # (K, 3, 3)
  local = CORNER_SIGNS[None, :4] * body.half_size[:, None, :]  # (K, 4, 3): pairs' first
  corner = jnp.einsum("kij,knj->kni", box_rot, local)  # relative to the centre, world
  corner = jnp.where(corner[..., 2:] <= 0.0, corner, -corner)
  depth = centre[:, None, 2] + corner[..., 2]
  active = (depth <= 0.0) & body.valid[:, None]
  point = centre[:, None] + corner
  point = point.at[..., 2].add(-0.5 * depth)
  depth, point, active = depth.reshape(-1), point.reshape(-1, 3), active.reshape(-1)
  if 0 < max_contacts < depth.shape[0]:
    _, keep = jax.lax.top_k(jnp.where(active, -depth, -jnp.inf), max_contacts)
    depth, point, active = depth[keep], point[keep], active[keep]
  return depth, point, active


def impedance(depth: jax.Array):
  """MuJoCo's stiffness, damping and impedance of a contact at this depth (`solimp`)."""
  timeconst = max(SOLREF[0], 2 * TIMESTEP)
  dmin, dmax, width, mid, power = SOLIMP
  k = 1.0 / (dmax * dmax * timeconst * timeconst * SOLREF[1] * SOLREF[1])
  b = 2.0 / (dmax * timeconst)
  x = jnp.abs(depth) / width
  y = jnp.where(x < mid, (1.0 / mid ** (power - 1)) * x ** power,
                1 - (1.0 / (1 - mid) ** (power - 1)) * jnp.clip(1 - x, 0.0) ** power)
  imp = jnp.where(x > 1.0, dmax, jnp.clip(dmin + y * (dmax - dmin), dmin, dmax))
  return k, b, imp


def _constraints(body: Body, qpos: jax.Array, rot: jax.Array, qvel: jax.Array,
                 max_contacts: int):
  """Pyramidal contact rows: J (R, 6), D (R,), aref (R,); inactive rows are zero."""
  depth, point, active = _contacts(body, qpos, rot, max_contacts)
  arm = point - qpos[:3]  # (C, 3)
  # d(point velocity)/d(qvel): [I | -skew(arm) rot], rows x, y, z of the world.
  rot_part = -jnp.einsum("cij,jk->cik", jax.vmap(_skew)(arm), rot)  # (C, 3, 3)
  jac = jnp.concatenate([jnp.broadcast_to(jnp.eye(3), rot_part.shape), rot_part], -1)
  normal, tangent1, tangent2 = jac[:, 2], jac[:, 1], -jac[:, 0]  # mju_makeFrame of +z
  edges = jnp.stack([normal + FRICTION * tangent1, normal - FRICTION * tangent1,
                     normal + FRICTION * tangent2, normal - FRICTION * tangent2], 1)
  edges = edges * active[:, None, None]  # (C, 4, 6)
  k, b, imp = impedance(depth)
  pos = depth * active
  invweight = (1.0 / body.mass) * (1 + FRICTION ** 2) * 2 * FRICTION ** 2  # / impratio 1
  d = 1.0 / jnp.maximum(invweight * (1 - imp) / imp, MINVAL)  # (C,)
  aref = -b * (edges @ qvel) - (k * imp * pos)[:, None]
  return (edges.reshape(-1, 6), jnp.repeat(d, 4), aref.reshape(-1))


def _quat_integrate(quat: jax.Array, omega_b: jax.Array, dt: float) -> jax.Array:
  """MuJoCo's mju_quatIntegrate: rotate by omega_b * dt about body axes, renormalise."""
  sq = jnp.sum(omega_b * omega_b)
  safe = jnp.where(sq > 0, sq, 1.0)
  norm = jnp.sqrt(safe)
  half = 0.5 * dt * norm
  # sin(half) / norm, with its limit dt / 2 at zero speed
  scale = jnp.where(sq > 0, jnp.sin(half) / norm, 0.5 * dt)
  w, v = jnp.cos(jnp.where(sq > 0, half, 0.0)), scale * omega_b
  a0, a = quat[0], quat[1:]
  out = jnp.concatenate([(a0 * w - jnp.dot(a, v))[None],
                         a0 * v + w * a + jnp.cross(a, v)])
  return out / jnp.linalg.norm(out)


def step(body: Body, state: State, wrench: jax.Array, *, iterations: int,
         ls_iterations: int, max_contacts: int = 0) -> State:
  """One step of 1/300 s: contacts, constraint solve, semi-implicit Euler.

  Products run in full float32 (`jax.default_matmul_precision`): on GPUs the default may
  be TF32, whose 10-bit mantissa costs millimetres through the stiff contacts.
  """
  with jax.default_matmul_precision("float32"):
    return _step(body, state, wrench, iterations, ls_iterations, max_contacts)


def _step(body, state, wrench, iterations, ls_iterations, max_contacts):
  qpos = state.qpos.at[3:].set(state.qpos[3:] / jnp.linalg.norm(state.qpos[3:]))
  rot = quat_to_mat(qpos[3:])
  m = _mass_matrix(body, rot)
  qfrc_smooth = _smooth_force(body, rot, state.qvel, wrench)
  qacc_smooth = cholesky_solve(m, qfrc_smooth)
  j, d, aref = _constraints(body, qpos, rot, state.qvel, max_contacts)
  problem = newton.Problem(m=m, qfrc_smooth=qfrc_smooth, qacc_smooth=qacc_smooth, j=j, d=d,
                           aref=aref, trace_m=jnp.maximum(jnp.trace(m), MINVAL))
  qacc = newton.solve(problem, state.qacc_warmstart, iterations, ls_iterations)
  qvel = state.qvel + TIMESTEP * qacc
  qpos = jnp.concatenate([qpos[:3] + TIMESTEP * qvel[:3],
                          _quat_integrate(qpos[3:], qvel[3:], TIMESTEP)])
  return State(qpos=qpos, qvel=qvel, qacc_warmstart=qacc)


def rollout(body: Body, qpos0: jax.Array, wrench: jax.Array, *, steps: int, duration: int,
            settings: BoxPlaneSettings) -> jax.Array:
  """(steps, 7) poses after each step of one push: `wrench` acts for `duration` steps."""
  zero = jnp.zeros(6, qpos0.dtype)
  state = State(qpos=qpos0, qvel=zero, qacc_warmstart=zero)
  n_push = min(steps, duration + settings.push_steps_extra)

  def stepper(iterations, ls_iterations):
    def one(state, t):
      applied = jnp.where(t < duration, wrench, 0.0)
      state = step(body, state, applied, iterations=iterations, ls_iterations=ls_iterations,
                   max_contacts=settings.max_contacts)
      return state, state.qpos
    return one

  state, head = jax.lax.scan(stepper(settings.push_iterations, settings.push_ls_iterations),
                             state, jnp.arange(n_push))
  _, tail = jax.lax.scan(stepper(settings.iterations, settings.ls_iterations), state,
                         jnp.arange(n_push, steps))
  return jnp.concatenate([head, tail], 0)


def rollout_object(prims: Primitives, pushes: Pushes, *, steps: int,
                   settings: BoxPlaneSettings, run_rollout=rollout) -> jax.Array:
  """(P, steps, 7) trajectories of one object (K slots) under P pushes; traceable.

  `run_rollout`: this module's `rollout`, or `box_plane_kernel.rollout` (the same
  contract; every rollout under any `vmap` of this function joins one kernel launch)."""
  body = body_of(prims)
  wrenches = push_wrenches(prims, pushes, mass_properties(prims))
  qpos0 = jnp.concatenate([rest_position(prims), jnp.array([1.0, 0.0, 0.0, 0.0])])
  run = functools.partial(run_rollout, body, qpos0.astype(jnp.float32), steps=steps,
                          duration=int(pushes.duration), settings=settings)
  return jax.vmap(run)(wrenches.astype(jnp.float32))
