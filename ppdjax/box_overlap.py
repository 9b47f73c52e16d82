"""Overlap of oriented boxes: IoU from exact volumes and a lattice count of the intersection."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.primitives import Primitives, corners, flatten, quat_to_mat, unflatten


def _inside(points: jax.Array, half_size, pos, quat) -> jax.Array:
  """Whether (N, 3) points lie in one box; (N,) bool."""
  local = (points - pos) @ quat_to_mat(quat)  # R^T (p - c)
  return jnp.all(jnp.abs(local) <= half_size, axis=-1)


def pair_iou(a: Primitives, b: Primitives, grid: int = 32) -> jax.Array:
  """IoU of two single boxes (fields without the K axis): exact volumes, grid intersection.

  The intersection volume is counted on a grid × grid × grid lattice of cell centres over
  the overlap of the two boxes' axis-aligned bounds; the union is |A| + |B| − |A ∩ B|.
  Axis-aligned boxes come out exact up to the lattice (error < 3/grid of the overlap); for
  rotated boxes the error is below 0.01 at grid = 32 (tested against Monte Carlo).
  """
  ca, cb = corners(a), corners(b)  # (8, 3) each
  lo = jnp.maximum(ca.min(0), cb.min(0))
  hi = jnp.minimum(ca.max(0), cb.max(0))
  extent = jnp.maximum(hi - lo, 0.0)
  u = (jnp.arange(grid, dtype=jnp.float32) + 0.5) / grid
  cells = jnp.stack(jnp.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3)
  points = lo + cells * extent
  both = (_inside(points, a.half_size, a.pos, a.quat)
          & _inside(points, b.half_size, b.pos, b.quat)).mean()
  inter = both * jnp.prod(extent)
  vol_a = 8.0 * jnp.prod(a.half_size)
  vol_b = 8.0 * jnp.prod(b.half_size)
  return inter / jnp.maximum(vol_a + vol_b - inter, 1e-12)


def box_iou(a: Primitives, b: Primitives, grid: int = 32) -> jax.Array:
  """(..., K, L) IoU of every box in `a` (..., K) with every box in `b` (..., L).

  Invalid boxes give 0. See `pair_iou` for the estimate and its error.
  """
  def one(a1, b1):
    return pair_iou(a1, b1, grid)
  rows = jax.vmap(jax.vmap(one, (None, 0)), (0, None))
  (flat_a, batch), (flat_b, _) = flatten(a), flatten(b)
  iou = unflatten(jax.vmap(rows)(flat_a, flat_b), batch)
  return jnp.where(a.valid[..., :, None] & b.valid[..., None, :], iou, 0.0)
