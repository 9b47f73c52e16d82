"""Where the voxels put box faces: the fit's unit-extent prior, and faces drawn within the
voxels' tolerance (the geometry half of +Fit+Sample, an option).

The voxelizer fills every voxel a box shares volume with, so a face lies within half a
voxel (16 mm) of the centre of its last filled voxel, where the voxel fit puts it: the
voxels cannot say where in that interval. Two things narrow or use that:

- `snap_unit_extent`: objects are normalised to a largest extent of exactly 1 m, so the
  faces that bound the object along its longest axis lie on the grid's boundary
  (`fit.fit_boxes(unit_extent=True)`).
- `spread_faces`: half a voxel of face error is enough for the densities to compensate
  (DESIGN.md, measured facts), so +Fit+Sample can draw each candidate's faces too: every
  face moves by an offset uniform in [-spread, spread] along its box's axis, faces that
  touch in the fit (a block's top and the bottom of the block it carries) move together,
  and the bounding box's centre stays where the fit has it (the object frame's origin,
  which the observed trajectories follow) with every face kept within the spread
  (`centred_move`): every candidate then voxelizes as the fitted boxes do. Candidate 0
  is the fitted boxes. Measured: closer trajectories, worse densities (off by default;
  docs/inference.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.infer.depth_fit import MIN_HALF, VOXEL, touching_faces
from ppdjax.primitives import Primitives, quat_to_mat

VOXEL_TOLERANCE = 0.5  # voxels: how far a face may be from where the voxel fit put it
CLIP_INSIDE = 0.99  # a re-centred face clipped back to its interval stops this far in


def bounds_centre(prims: Primitives) -> jax.Array:
  """(3,) the centre of the valid boxes' axis-aligned bounding box (0 without boxes)."""
  rot = quat_to_mat(prims.quat)
  reach = jnp.einsum("kij,kj->ki", jnp.abs(rot), prims.half_size)  # half extents, world axes
  valid = prims.valid[:, None]
  lo = jnp.where(valid, prims.pos - reach, jnp.inf).min(0)
  hi = jnp.where(valid, prims.pos + reach, -jnp.inf).max(0)
  return jnp.where(jnp.isfinite(lo) & jnp.isfinite(hi), 0.5 * (lo + hi), 0.0)


def recentre(prims: Primitives, centre=0.0) -> Primitives:
  """`prims` (K) shifted so that the valid boxes' axis-aligned bounding box is centred on
  `centre` (3,) (default: the origin)."""
  shift = bounds_centre(prims) - centre
  return prims.replace(pos=jnp.where(prims.valid[:, None], prims.pos - shift, prims.pos))


def move_faces(prims: Primitives, offsets_Kx6: jax.Array) -> Primitives:
  """`prims` (K) with each box's lo (columns 0-2) and hi (3-5) faces moved by `offsets`
  (m) along its own axes, half sizes kept >= MIN_HALF."""
  rot = quat_to_mat(prims.quat)
  lo = -prims.half_size + offsets_Kx6[:, :3]
  hi = jnp.maximum(prims.half_size + offsets_Kx6[:, 3:], lo + 2 * MIN_HALF)
  valid = prims.valid[:, None]
  half = jnp.where(valid, 0.5 * (hi - lo), prims.half_size)
  pos = jnp.where(valid, prims.pos + jnp.einsum("kij,kj->ki", rot, 0.5 * (hi + lo)), prims.pos)
  return prims.replace(half_size=half, pos=pos)


def face_positions(prims: Primitives) -> tuple[jax.Array, jax.Array]:
  """(K, 6) where each face's centre lies along the world axis its box axis is closest to
  (lo faces, then hi), and (K, 6) that axis: exact for axis-aligned boxes."""
  rot = quat_to_mat(prims.quat)  # columns: box axes in world coordinates
  axis = jnp.argmax(jnp.abs(rot), 1)  # (K, 3): the world axis of each box axis
  along = jnp.take_along_axis(rot, axis[:, None, :], 1)[:, 0]  # (K, 3): rot[k, axis, j]
  centre = jnp.take_along_axis(prims.pos, axis, 1)  # (K, 3)
  reach = along * prims.half_size
  return jnp.concatenate([centre - reach, centre + reach], -1), jnp.concatenate([axis, axis], -1)


def snap_unit_extent(prims: Primitives, vox_XYZ: jax.Array) -> Primitives:
  """One object's boxes `prims` (K) with the faces that bound it along its longest axis at
  ±0.5 m, where the voxels (R, R, R) say which axis that is.

  Objects are normalised to a largest extent of exactly 1 m (DESIGN.md), so along that
  axis the object spans the grid and its bounding faces lie on the grid's boundary; the
  voxels alone place them only within half a voxel (16 mm short of the boundary, at the
  centre of the last voxel). When one axis alone spans the grid it is the longest; when two
  or three do (11 % and 1 % of random towers), which one is 1 m is unknown and nothing
  moves. Nor does a bounding face that several boxes reach alike (the voxels cannot tell
  which of them is the one on the boundary: moving all would double the others' error). A
  box's face moves along the box axis closest to the world axis, by what brings the box's
  extent to the boundary (exact for axis-aligned boxes)."""
  occ = vox_XYZ.astype(bool)
  full = jnp.stack([occ.any((1, 2)).all(), occ.any((0, 2)).all(), occ.any((0, 1)).all()])
  snap = full & (full.sum() == 1)  # (3,)
  rot = quat_to_mat(prims.quat)
  reach = jnp.einsum("kij,kj->ki", jnp.abs(rot), prims.half_size)  # world half extents
  valid = prims.valid[:, None]
  top, bottom = prims.pos + reach, prims.pos - reach
  g_top = jnp.where(valid, top, -jnp.inf).max(0)
  g_bottom = jnp.where(valid, bottom, jnp.inf).min(0)
  offsets = jnp.zeros((prims.num_slots, 6))
  for a in range(3):
    j = jnp.argmax(jnp.abs(rot[:, a, :]), -1)  # (K,): the box axis closest to world axis a
    c = jnp.take_along_axis(rot[:, a, :], j[:, None], 1)[:, 0]
    scale = 1.0 / jnp.maximum(jnp.abs(c), 1e-6)
    at_top = prims.valid & (top[:, a] >= g_top[a] - 1e-6)
    at_bottom = prims.valid & (bottom[:, a] <= g_bottom[a] + 1e-6)
    grow_hi = jnp.where(snap[a] & at_top & (at_top.sum() == 1),
                        (0.5 - top[:, a]) * scale, 0.0)  # outward along +a
    grow_lo = jnp.where(snap[a] & at_bottom & (at_bottom.sum() == 1),
                        (bottom[:, a] + 0.5) * scale, 0.0)  # outward along -a
    # outward along +a is the box's hi face where its axis j points along +a, else its lo
    hi_col, lo_col = jnp.where(c > 0, 3 + j, j), jnp.where(c > 0, j, 3 + j)
    sign_hi, sign_lo = jnp.where(c > 0, 1.0, -1.0), jnp.where(c > 0, -1.0, 1.0)
    rows = jnp.arange(prims.num_slots)
    offsets = offsets.at[rows, hi_col].add(sign_hi * grow_hi)
    offsets = offsets.at[rows, lo_col].add(sign_lo * grow_lo)
  return move_faces(prims, offsets)


def centred_move(prims: Primitives, offsets_Kx6: jax.Array, limit) -> Primitives:
  """`move_faces`, keeping the bounding box's centre where `prims` has it (the object
  frame's origin): the moved boxes' shift of that centre is taken off every face (along
  each box's axes), each offset clipped to [-limit, limit] (m, scalar or (K, 6)) again,
  and the result re-centred there (the clip moves no face that bounds the object)."""
  centre = bounds_centre(prims)
  shift = bounds_centre(move_faces(prims, offsets_Kx6)) - centre  # (3,) world
  along = jnp.einsum("kji,j->ki", quat_to_mat(prims.quat), shift)  # along each box's axes
  inside = CLIP_INSIDE * jnp.asarray(limit)  # the interval's ends are open: stay inside it
  offsets = jnp.clip(offsets_Kx6 - jnp.concatenate([along, along], -1), -inside, inside)
  return recentre(move_faces(prims, offsets), centre)


def check_spread(spread: float, fit: bool = True) -> None:
  """ValueError unless 0 <= spread <= VOXEL_TOLERANCE (voxels: beyond it faces would leave
  the interval the voxels allow), and unless there is a fit to move (`fit`) where > 0."""
  if not 0 <= spread <= VOXEL_TOLERANCE:
    raise ValueError(f"face_spread must be in [0, {VOXEL_TOLERANCE}] voxels (how far the "
                     f"voxels allow a face to be), got {spread}")
  if spread > 0 and not fit:
    raise ValueError("face_spread moves fitted faces: it needs fit=True")


def tie_offsets(offsets_SxKx6: jax.Array, ties_KxKx3: jax.Array) -> jax.Array:
  """Offsets with each lo face that touches a box's hi face (`depth_fit.touching_faces`: i's hi
  touches j's lo along axis a) set to that hi face's offset (the first such box), so
  touching faces stay touching."""
  lo, hi = offsets_SxKx6[..., :3], offsets_SxKx6[..., 3:]
  tied = ties_KxKx3.any(0)  # (K, 3): j's lo face along a touches some box's hi face
  partner = jnp.argmax(ties_KxKx3, 0)  # (K, 3): the first such box i
  partner_hi = jnp.take_along_axis(hi, partner[None], -2)  # (S, K, 3): hi[s, partner[j, a], a]
  return jnp.concatenate([jnp.where(tied, partner_hi, lo), hi], -1)


def spread_faces(prims: Primitives, key: jax.Array, num: int,
                 spread: float = VOXEL_TOLERANCE) -> Primitives:
  """`num` copies (S, K) of one object's boxes `prims` (K) with their faces drawn uniform
  within `spread` voxels of where they are (0 < spread <= VOXEL_TOLERANCE), touching faces
  together (candidate 0: `prims` itself)."""
  check_spread(spread)
  k = prims.num_slots
  # faces on the grid's boundary stay (`snap_unit_extent` put them there: they are known)
  where, _ = face_positions(prims)
  limit = jnp.where(jnp.abs(where) > 0.5 - 1e-5, 0.0, spread * VOXEL)
  offsets = limit * jax.random.uniform(key, (num, k, 6), minval=-1.0, maxval=1.0)
  offsets = tie_offsets(offsets.at[0].set(0.0), touching_faces(prims))
  return jax.vmap(centred_move, in_axes=(None, 0, None))(prims, offsets, limit)
