"""An unlimited stream of tower geometries for the voxel-only geometry stage, made on the device.

Geometry needs no rendering and no simulation: each batch samples fresh towers (the
distribution of `towers.sample_geometry` with rotate = 0), voxelizes them with the exact
occupancy rule of `voxels.voxelize` specialised to axis-aligned boxes (three 1-D overlap
tests instead of fifteen separating axes), and may apply one of the eight symmetries of
the square about z (x/y flips and the x<->y swap; quarter turns are their products). All
of it is one jittable function of a PRNG key, so a stream batch is a function of the step.

These symmetries preserve the labels' meaning only for what the voxels show: an image or
a trajectory would not turn with them, so augmentation is for voxel-only training.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ppdjax.conventions import NUM_SLOTS, VOXEL_RESOLUTION
from ppdjax.dataset.towers import HEIGHT_RANGE, WIDTH_RANGE
from ppdjax.dataset.voxels import TOUCH, voxel_centers
from ppdjax.primitives import Primitives, mat_to_quat, quat_to_mat

GEOMETRY_DENSITY = 1000.0  # kg/m^3 placeholder: the stream trains no density


def sample_towers_jax(key: jax.Array, batch: int, num_slots: int = NUM_SLOTS) -> Primitives:
  """(batch, K) random axis-aligned towers of 2..K blocks, as `towers.sample_geometry`.

  Block k+1's centre is N(centre_k, extent_k / 4) in x and y and it rests on block k;
  the tower is scaled so its largest extent is 1 and centred on its bounding box.
  """
  kn, kw, kh, kx = jax.random.split(key, 4)
  n = jax.random.randint(kn, (batch,), 2, num_slots + 1)
  wd = jax.random.uniform(kw, (batch, num_slots, 2), minval=WIDTH_RANGE[0],
                          maxval=WIDTH_RANGE[1])
  h = jax.random.uniform(kh, (batch, num_slots, 1), minval=HEIGHT_RANGE[0],
                         maxval=HEIGHT_RANGE[1])
  size = jnp.concatenate([wd, h], -1)
  steps = jax.random.normal(kx, (batch, num_slots - 1, 2)) * size[:, :-1, :2] / 4
  xy = jnp.concatenate([jnp.zeros((batch, 1, 2)), jnp.cumsum(steps, 1)], 1)
  z = jnp.cumsum(h, 1) - h / 2
  pos = jnp.concatenate([xy, z], -1)
  valid = jnp.arange(num_slots) < n[:, None]
  lo = jnp.where(valid[..., None], pos - size / 2, jnp.inf).min(1, keepdims=True)
  hi = jnp.where(valid[..., None], pos + size / 2, -jnp.inf).max(1, keepdims=True)
  scale = 1.0 / (hi - lo).max(-1, keepdims=True)
  keep = valid[..., None]
  return Primitives(
      half_size=jnp.where(keep, size / 2 * scale, 0.0),
      pos=jnp.where(keep, (pos - (lo + hi) / 2) * scale, 0.0),
      quat=jnp.broadcast_to(jnp.array([1.0, 0, 0, 0]), (batch, num_slots, 4)),
      density=jnp.where(valid, GEOMETRY_DENSITY, 0.0), valid=valid)


def voxelize_axis_aligned(prims: Primitives, resolution: int = VOXEL_RESOLUTION) -> jax.Array:
  """(..., R, R, R) bool occupancy of axis-aligned boxes (quaternions ignored).

  The rule of `voxels.voxelize`: a voxel is filled when it shares volume with a valid box,
  i.e. along every axis its centre is closer to the box centre than the box's half size
  plus half a voxel (less the same touching tolerance).
  """
  c = jnp.asarray(voxel_centers(resolution)[:, 0, 0, 0])  # (R,)
  reach = prims.half_size + 0.5 / resolution - TOUCH  # (..., K, 3)
  inside = jnp.abs(c - prims.pos[..., None]) < reach[..., None]  # (..., K, 3, R)
  x, y, z = inside[..., 0, :], inside[..., 1, :], inside[..., 2, :]
  cell = x[..., :, None, None] & y[..., None, :, None] & z[..., None, None, :]
  return (cell & prims.valid[..., None, None, None]).any(-4)


def symmetry(code: jax.Array) -> jax.Array:
  """(3, 3) the symmetry of the square about z numbered `code` in 0..7: bit 0 flips x,
  bit 1 flips y (both: a half turn), bit 2 swaps x and y first (with one flip: a quarter turn)."""
  swap = jnp.where((code >> 2) & 1, jnp.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]),
                   jnp.eye(3))
  flip = jnp.diag(jnp.array([jnp.where(code & 1, -1.0, 1.0), jnp.where((code >> 1) & 1,
                                                                       -1.0, 1.0), 1.0]))
  return flip @ swap


def transform(voxels_RRR: jax.Array, prims: Primitives, code: jax.Array):
  """One object's voxels and boxes under `symmetry(code)`: (voxels, Primitives).

  A box (c, R, h) maps to (M c, M R Mᵀ, |M| h): M R Mᵀ is a proper rotation even when M
  is a reflection, so every symmetry maps boxes to boxes. The grid is centred on the
  origin, so the voxels transform by index flips and a transpose.
  """
  m = symmetry(code)
  v = jnp.where((code >> 2) & 1, jnp.swapaxes(voxels_RRR, 0, 1), voxels_RRR)
  v = jnp.where(code & 1, v[::-1], v)
  v = jnp.where((code >> 1) & 1, v[:, ::-1], v)
  rot = m @ quat_to_mat(prims.quat) @ m.T
  quat = jax.vmap(mat_to_quat)(rot)
  half = prims.half_size @ jnp.abs(m).T
  keep = prims.valid[:, None]
  return v, prims.replace(pos=jnp.where(keep, prims.pos @ m.T, 0.0),
                          half_size=jnp.where(keep, half, 0.0), quat=quat)


def augment(key: jax.Array, voxels: jax.Array, prims: Primitives):
  """A batch (B, R, R, R) / (B, K) under one random symmetry of the square per object."""
  codes = jax.random.randint(key, (voxels.shape[0],), 0, 8)
  return jax.vmap(transform)(voxels, prims, codes)


@functools.partial(jax.jit, static_argnums=(1, 2))
def geometry_batch(key: jax.Array, batch: int, augmented: bool = True) -> dict:
  """A training batch of fresh towers: {"voxels": (B, 32, 32, 32) uint8, "primitives"}."""
  k_towers, k_aug = jax.random.split(key)
  prims = sample_towers_jax(k_towers, batch)
  voxels = voxelize_axis_aligned(prims)
  if augmented:  # fresh towers need none; kept so that finite pools and the stream match
    voxels, prims = augment(k_aug, voxels, prims)
  return {"voxels": voxels.astype(jnp.uint8), "primitives": prims}
