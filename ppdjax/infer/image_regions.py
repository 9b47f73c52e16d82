"""Where in the image an object can appear (`object_window`), where a face's sweep can
change anything, and the edge score summed there only: the image fit scores ~50
positions of each face, and a face moving within a voxel changes the labels of a small
part of the image (its slab, and the slab's shadow).

The score of a sweep's positions is compared among themselves only (`sweep_faces`), so
pixels whose labels no position changes add the same to each: leaving them out keeps
every comparison. The region is a rectangle of the object window (`changed_rect`); the
score walks it in tiles of a fixed size (`tiled_edge_score`), so that the work follows the
region's size while every array keeps a static shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.dataset.camera import check_camera
from ppdjax.dataset.depth import to_world
from ppdjax.infer.depth_fit import boxes_from_faces
from ppdjax.primitives import Primitives, quat_to_mat

SHIFT_TOL = 1e-6  # m: a box that moves more than this between a sweep's ends moved
MARGIN = 1  # pixels around the projected region: each changed pixel's pairs lie inside
# Tiles on a CPU: the example tower's image fit took 1.3 s warm with 24 x 48 or 16 x 64,
# and 16 s with 32 x 32, the same work laid out otherwise by XLA (time a new tile size
# before choosing it: experiments/results/benchmarks.md). On a GPU one tile the size of
# the window: tiles were 1.2-2x slower there (a loop of small kernels).
CPU_TILE = (24, 48)


def object_window(camera: dict, margin: int = 2, light=None) -> tuple[int, int, int, int]:
  """Rows [r0, r1) and columns [c0, c1) of the camera's image where an object can appear:
  the projection of the space objects occupy (the unit cube on the ground, centred over
  the origin: the dataset's convention), and with `light` (its direction) the cube's
  shadow on the floor, `margin` pixels wider, clipped to the image."""
  cam = check_camera(camera)
  corners = np.stack(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [0.0, 1.0]), -1).reshape(-1, 3)
  if light is not None:  # where the light's rays through the corners meet the floor
    light = np.asarray(light, np.float64)
    corners = np.concatenate([corners, corners - corners[:, 2:] / light[2] * light])
  t = np.asarray(cam["camera_from_world"], np.float64)
  p = (corners @ t[:3, :3].T + t[:3, 3]) @ np.asarray(cam["intrinsics"], np.float64).T
  h, w = cam["height"], cam["width"]
  if np.any(p[:, 2] <= 1e-6):  # a long shadow reaches behind the camera: score everything
    return 0, h, 0, w
  u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]  # pixel coordinates (edges at integers)
  return (max(0, int(np.floor(v.min())) - margin), min(h, int(np.ceil(v.max())) + margin),
          max(0, int(np.floor(u.min())) - margin), min(w, int(np.ceil(u.max())) + margin))


def face_corners(boxes: Primitives) -> jax.Array:
  """(K, 6, 4, 3) the corners of each box's faces (`metrics.FACE_NAMES` order) in the
  world, the boxes (object frame) standing at rest."""
  world = to_world(boxes)
  rot = quat_to_mat(world.quat)
  signs = [(-1, -1), (-1, 1), (1, -1), (1, 1)]  # the corners across the face's two axes
  local = np.zeros((6, 4, 3), np.float32)  # in units of the half sizes
  for face in range(6):
    axis = face % 3
    local[face, :, axis] = 1.0 if face >= 3 else -1.0
    local[face][:, [a for a in range(3) if a != axis]] = signs
  points = local[None] * world.half_size[:, None, None, :]  # (K, 6, 4, 3)
  return jnp.einsum("kij,kfcj->kfci", rot, points) + world.pos[:, None, None, :]


def changed_rect(prims: Primitives, faces_a, faces_b, move_Kx6, project, window_hw,
                 light=None) -> jax.Array:
  """(4,) int [r0, r1, c0, c1): the pixels of the window (h, w) whose labels can differ
  between any two positions of a sweep that moves faces `move_Kx6` from `faces_a` to
  `faces_b` (each a (K, 6) face array of `boxes_from_faces(prims, .)`), `MARGIN` wider.

  The moved faces sweep slabs between their positions at the two ends; a ray's first hit
  changes only if it crosses a slab, and a point's shadow (with `light`) only if it lies
  on a light ray through one, between the slab and the floor: the rectangle holds the
  projections of the slabs' corners and of their shadows on the floor. If the object
  itself moves (a moved face becomes its lowest point, and it stands elsewhere), or a
  point lies behind the camera, the whole window. `project` maps world points (..., 3)
  to window pixel coordinates (u along columns, v along rows) and their depth."""
  h, w = window_hw
  ends = [boxes_from_faces(prims, f) for f in (faces_a, faces_b)]
  corners = jnp.stack([face_corners(b) for b in ends], 2)  # (K, 6, 2, 4, 3)
  moved = (move_Kx6 > 0) & prims.valid[:, None]
  points = corners.reshape(corners.shape[:2] + (8, 3))
  if light is not None:
    light = jnp.asarray(light, jnp.float32)
    shadow = points - points[..., 2:] / light[2] * light  # along the light, onto z = 0
    points = jnp.concatenate([points, shadow], 2)
  u, v, z = project(points)  # each (K, 6, P)
  mask = jnp.broadcast_to(moved[..., None], u.shape)
  big = jnp.float32(1e9)
  lo_u, hi_u = jnp.where(mask, u, big).min(), jnp.where(mask, u, -big).max()
  lo_v, hi_v = jnp.where(mask, v, big).min(), jnp.where(mask, v, -big).max()
  world_a, world_b = (to_world(b).pos for b in ends)
  still = ~jnp.any(moved, -1) & prims.valid
  shifted = jnp.any(still & (jnp.abs(world_a - world_b).max(-1) > SHIFT_TOL))
  behind = jnp.any(mask & (z <= 1e-6))
  rect = jnp.stack([jnp.floor(lo_v) - MARGIN, jnp.ceil(hi_v) + MARGIN,
                    jnp.floor(lo_u) - MARGIN, jnp.ceil(hi_u) + MARGIN])
  rect = jnp.clip(rect, 0, jnp.array([h, h, w, w], jnp.float32)).astype(jnp.int32)
  whole = jnp.array([0, h, 0, w], jnp.int32)
  empty = ~jnp.any(mask)  # nothing moves: a single tile scores the same everywhere
  return jnp.where(shifted | behind, whole,
                   jnp.where(empty, jnp.array([0, 1, 0, 1], jnp.int32), rect))


def window_projector(intrinsics, camera_from_world, window):
  """`project` for `changed_rect`: world points to pixel coordinates of the window
  (r0, r1, c0, c1) (pixel edges at integers) and depth."""
  r0, _, c0, _ = window

  def project(points):
    cam = points @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    p = cam @ intrinsics.T
    z = p[..., 2]
    safe = jnp.where(z > 1e-6, z, 1.0)
    return p[..., 0] / safe - c0, p[..., 1] / safe - r0, z

  return project


def tiled_edge_score(labels, rect, across_HW, down_HW, tile) -> jax.Array:
  """`image_edges.edge_score` summed over the pixels of `rect` (and the tiles' spill past
  it, the same for every position of a sweep), without the pixel pairs elsewhere.

  Args:
    labels: ray indices (M,) into the window's rays (rows of width W) -> labels (M,).
    rect: (4,) int [r0, r1, c0, c1) within the window (`changed_rect`).
    across_HW, down_HW: the window's edge strengths (`image_edges.edge_strength`).
    tile: (rows, columns) of each tile; each renders one more row and column (above and
      left) for its pixels' pairs.
  """
  h, w = across_HW.shape
  th, tw = tile
  pad = lambda x: jnp.pad(x, ((0, th), (0, tw)))  # beyond the window: strength 0
  across, down = pad(across_HW), pad(down_HW)
  n_rows = (rect[1] - rect[0] + th - 1) // th
  n_cols = (rect[3] - rect[2] + tw - 1) // tw
  n_cols = jnp.maximum(n_cols, 1)

  def one(i, total):
    r = rect[0] + (i // n_cols) * th
    c = rect[2] + (i % n_cols) * tw
    rows = jnp.clip(r - 1 + jnp.arange(th + 1), 0, h - 1)
    cols = jnp.clip(c - 1 + jnp.arange(tw + 1), 0, w - 1)
    lab = labels((rows[:, None] * w + cols[None, :]).reshape(-1)).reshape(th + 1, tw + 1)
    core = lab[1:, 1:]
    a = jax.lax.dynamic_slice(across, (r, c), (th, tw))
    d = jax.lax.dynamic_slice(down, (r, c), (th, tw))
    return total + (jnp.sum(jnp.where(core != lab[1:, :-1], a, 0))
                    + jnp.sum(jnp.where(core != lab[:-1, 1:], d, 0)))

  return -jax.lax.fori_loop(0, n_rows * n_cols, one, jnp.int32(0))
