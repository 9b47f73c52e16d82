"""Boxes read from 32^3 voxels: input checks, the output convention, the exact tower reading.

A z-slice of an axis-aligned tower is one block's rectangle or, where an interface lies
inside the slice ("straddling"), the union of two (the voxelizer fills voxels that share
volume with a box). Runs of identical pure slices are blocks; a straddling slice belongs to
both. Faces go at the centres of the first/last occupied voxels (along z, of the slices
touching the block); runs meeting with no straddling slice meet inside the slice of the
containing rectangle if nested, else on the voxel boundary. Limits: stacked blocks with
identical voxel rectangles read as one; of more than K runs the K largest are kept; blocks
under 2 voxels tall may have no pure slice. `fit.fit_boxes` builds on this reading.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import NUM_SLOTS, VOXEL_RESOLUTION as R
from ppdjax.primitives import Primitives, bottom_to_top, canonical_boxes, unflatten

VOXEL = 1.0 / R  # m
PLACEHOLDER_DENSITY = 1000.0  # kg/m^3 of the returned boxes; callers put densities on
IDENTITY = np.float32([1, 0, 0, 0])


def check_voxels(voxels, init: Primitives | None = None) -> tuple[int, ...]:
  """Batch shape of (B..., 32, 32, 32) `voxels`; ValueError naming the problem if bad.

  Values (exactly 0/1, no empty grid) are checked only on concrete arrays (not under jit).
  """
  shape = tuple(np.shape(voxels))
  dtype = np.dtype(voxels.dtype if hasattr(voxels, "dtype") else np.asarray(voxels).dtype)
  if len(shape) < 3 or shape[-3:] != (R, R, R):
    raise ValueError(f"voxels: expected shape (..., {R}, {R}, {R}), got {shape}")
  if not (dtype == np.bool_ or np.issubdtype(dtype, np.integer)
          or np.issubdtype(dtype, np.floating)):
    raise ValueError(f"voxels: expected a bool, integer or 0/1 float dtype, got {dtype}")
  if not isinstance(voxels, jax.core.Tracer):
    v = np.asarray(voxels)
    if dtype != np.bool_ and not np.all((v == 0) | (v == 1)):
      raise ValueError(f"voxels: values must be exactly 0 or 1 (binary occupancy); got "
                       f"{dtype} values in [{v.min()}, {v.max()}]")
    empty = ~v.reshape(-1, R ** 3).astype(bool).any(-1)
    if empty.any():
      raise ValueError(f"voxels: {int(empty.sum())} of {empty.size} grids are all empty "
                       f"(first at flat index {int(np.argmax(empty))}); nothing to fit")
  if init is not None and tuple(init.batch_shape) != shape[:-3]:
    raise ValueError(f"init: batch shape {tuple(init.batch_shape)} does not match the "
                     f"voxels' batch shape {shape[:-3]}")
  return shape[:-3]


def as_bool(v: jax.Array) -> jax.Array:
  return v > 0.5 if jnp.issubdtype(v.dtype, jnp.floating) else v != 0


def finish_boxes(half, pos, quat, valid) -> Primitives:
  """One object's Primitives: canonical labels, bottom to top, padding cleared."""
  p = bottom_to_top(canonical_boxes(Primitives(half, pos, quat, jnp.ones(valid.shape), valid)))
  v = p.valid[:, None]
  return Primitives(half_size=jnp.where(v, p.half_size, 0.0), pos=jnp.where(v, p.pos, 0.0),
                    quat=jnp.where(v, p.quat, IDENTITY),
                    density=jnp.where(p.valid, PLACEHOLDER_DENSITY, 0.0), valid=p.valid)


def _center(i):
  """Centre (m) of voxel index i along an axis."""
  return (i + 0.5) * VOXEL - 0.5


def _down(a):
  """a[z - 1] at z (zeros at z = 0)."""
  return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]])


def _up(a):
  """a[z + 1] at z (zeros at the top)."""
  return jnp.concatenate([a[1:], jnp.zeros_like(a[:1])])


def read_one(vox_XYZ: jax.Array, num_slots: int, tol: float = 0.0) -> Primitives:
  """`read_tower` of one (R, R, R) bool grid; slice masks match at IoU >= 1 - tol."""
  s = jnp.moveaxis(vox_XYZ, -1, 0)  # (Z, X, Y) slices
  size = lambda a: jnp.sum(a, axis=(-2, -1))
  same = lambda a, b: size(a & b) >= (1 - tol) * jnp.maximum(size(a | b), 1)
  within = lambda a, b: ~jnp.any(a & ~b, axis=(-2, -1))
  occ, below, above = s.any((-2, -1)), _down(s), _up(s)
  straddle = (occ & _down(occ) & _up(occ) & same(s, below | above) & ~same(s, below)
              & ~same(s, above))  # the union of two different neighbours
  pure = occ & ~straddle
  start = pure & ~(_down(pure) & same(s, below))
  member = jnp.where(pure, jnp.cumsum(start) - 1, -1)[:, None] == jnp.arange(R)  # (Z, runs)
  count = jnp.einsum("zr,z->r", member, size(s))
  z = jnp.arange(R)[:, None]
  lo, hi = jnp.where(member, z, R).min(0), jnp.where(member, z, -1).max(0)
  mask = jnp.einsum("zr,zxy->rxy", member.astype(jnp.int32), s.astype(jnp.int32)) > 0

  def face(end, step):
    """z face (m) of each run beyond its first (step -1) or last (step 1) pure slice."""
    nb = jnp.clip(end + step, 0, R - 1)
    inside = (end + step >= 0) & (end + step < R)
    here, there = _center(jnp.clip(end, 0, R - 1).astype(jnp.float32)), _center(nb * 1.0)
    mine, theirs = s[jnp.clip(end, 0, R - 1)], s[nb]
    touching = jnp.where(within(mine, theirs), there,  # interface in the neighbour's slice
                         jnp.where(within(theirs, mine), here, here + step * VOXEL / 2))
    return jnp.where(inside & straddle[nb], there,
                     jnp.where(inside & pure[nb], touching, here))

  first = lambda m: _center(jnp.argmax(m, -1))
  last = lambda m: _center(R - 1 - jnp.argmax(m[:, ::-1], -1))
  xs, ys = mask.any(2), mask.any(1)  # (runs, X), (runs, Y)
  lo3 = jnp.stack([first(xs), first(ys), face(lo, -1)], -1)
  hi3 = jnp.stack([last(xs), last(ys), face(hi, 1)], -1)
  _, keep = jax.lax.top_k(count, num_slots)  # the largest runs
  return finish_boxes((hi3 - lo3)[keep] / 2, (hi3 + lo3)[keep] / 2,
                 jnp.broadcast_to(IDENTITY, (num_slots, 4)), count[keep] > 0)


@functools.partial(jax.jit, static_argnums=1)
def _read_batch(vox_NxRxRxR, num_slots: int) -> Primitives:
  return jax.vmap(lambda x: read_one(x, num_slots))(as_bool(vox_NxRxRxR))


def read_tower(voxels, num_slots: int = NUM_SLOTS) -> Primitives:
  """Reads axis-aligned towers exactly from the z-profile of their voxels.

  Args:
    voxels: (B..., 32, 32, 32) occupancy indexed [x, y, z]; bool, integer or 0/1 float.
    num_slots: K, boxes per object (with more runs of slices, the K largest are kept).

  Returns:
    Primitives (B..., K): axis-aligned boxes bottom to top, density 1000 (placeholder),
    padding last (half size 0, pos 0, identity quat). An empty grid gives no valid box.
  """
  batch = check_voxels(voxels)
  return unflatten(_read_batch(jnp.asarray(voxels).reshape(-1, R, R, R), num_slots), batch)
