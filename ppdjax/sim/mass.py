"""Differentiable mass properties of a union of boxes, and their principal axes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ppdjax.primitives import Primitives, mat_to_quat, quat_mul, quat_to_mat, check


@struct.dataclass
class MassProperties:
  """Rigid-body mass properties in the object frame (batches add leading axes).

  Attributes:
    mass: (...) kg.
    com: (..., 3) centre of mass, object frame, metres.
    inertia: (..., 3, 3) inertia tensor about the centre of mass, object axes, kg m^2.
  """

  mass: jax.Array
  com: jax.Array
  inertia: jax.Array


def box_masses(prims: Primitives) -> jax.Array:
  """(..., K) mass of each box; zero for invalid slots."""
  volume = 8.0 * jnp.prod(prims.half_size, axis=-1)
  return jnp.where(prims.valid, prims.density * volume, 0.0)


def mass_properties(prims: Primitives) -> MassProperties:
  """Mass, centre of mass and inertia about it for boxes of per-box density (and, where
  given, each box's `inertia_scale`: a hollow block's inertia over a uniform one's).

  Pure JAX: works under jit, vmap, grad and jacfwd; invalid boxes contribute nothing.
  Matches MuJoCo's compiler for a body of box geoms with a `density` attribute.

  Concrete boxes are checked first (`Primitives.validate`: ValueError naming the field for
  a negative half size, a quaternion that is not unit, a NaN); traced ones are the
  caller's contract (the jitted pipeline makes them from validated inputs).
  """
  check(prims)
  if prims.density.ndim > 1:
    return jax.vmap(mass_properties)(prims)
  m_k = box_masses(prims)
  mass = m_k.sum()
  com = (m_k[:, None] * prims.pos).sum(0) / mass
  h2 = prims.half_size ** 2
  diag_k = m_k[:, None] / 3.0 * jnp.stack(
      [h2[:, 1] + h2[:, 2], h2[:, 0] + h2[:, 2], h2[:, 0] + h2[:, 1]], -1)
  if prims.inertia_scale is not None:  # blocks not uniform (hollow): same mass and centre
    diag_k = diag_k * prims.inertia_scale[:, None]
  rot = quat_to_mat(prims.quat)
  inertia_k = jnp.einsum("kij,kj,klj->kil", rot, diag_k, rot)
  d = prims.pos - com
  eye = jnp.eye(3, dtype=d.dtype)
  shift_k = m_k[:, None, None] * ((d * d).sum(-1)[:, None, None] * eye
                                  - d[:, :, None] * d[:, None, :])
  return MassProperties(mass=mass, com=com, inertia=(inertia_k + shift_k).sum(0))


# Eigenvalue gaps below this (relative to the trace) count as degenerate in derivatives.
_DEGENERATE_GAP = 1e-6


@jax.custom_jvp
def principal_axes(inertia: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Principal moments (3,) and the quaternion (4,) of the principal frame of a 3x3 inertia.

  MuJoCo stores a body's inertia as diagonal moments in a frame `body_iquat`. The custom
  JVP keeps forward-mode derivatives finite where moments coincide (symmetric objects):
  within an exactly degenerate pair the rotation derivative is set to zero, so only the
  moments move (the tensor's derivative is then exact unless the perturbation mixes the
  degenerate axes).
  """
  moments, axes = _eigh_proper(inertia)
  return moments, mat_to_quat(axes)


def _eigh_proper(inertia):
  moments, axes = jnp.linalg.eigh(0.5 * (inertia + inertia.T))
  flip = jnp.where(jnp.linalg.det(axes) < 0, -1.0, 1.0)
  return moments, axes.at[:, 2].multiply(flip)


@principal_axes.defjvp
def _principal_axes_jvp(primals, tangents):
  (inertia,), (d_inertia,) = primals, tangents
  moments, axes = _eigh_proper(inertia)
  quat = mat_to_quat(axes)
  a = axes.T @ (0.5 * (d_inertia + d_inertia.T)) @ axes
  gap = moments[None, :] - moments[:, None]  # gap[i, j] = λj - λi
  tol = _DEGENERATE_GAP * jnp.abs(moments).sum()
  safe = jnp.where(jnp.abs(gap) > tol, gap, 1.0)
  omega = jnp.where(jnp.abs(gap) > tol, a / safe, 0.0)  # d(axes) = axes @ omega
  w_body = jnp.stack([omega[2, 1], omega[0, 2], omega[1, 0]])
  d_quat = 0.5 * quat_mul(quat, jnp.concatenate([jnp.zeros(1, w_body.dtype), w_body]))
  return (moments, quat), (jnp.diag(a), d_quat)
