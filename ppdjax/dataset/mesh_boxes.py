"""Ground-truth primitives of a mesh, by the paper's recipe (Sec. 5.2).

The paper fits boxes to a tool's point cloud by minimising an energy, then assigns each
vertex to its nearest box and refines each box to the minimum oriented bounding box of its
vertices. Here, on area-weighted surface samples of the normalised mesh:

1. **Start**: one box per part (the minimum oriented bounding box of its samples); with
   more parts than `max_boxes`, the pair whose merged box adds the least volume merges
   first.
2. **Energy** E = total box volume (each box as tight as its points allow) + `box_cost`
   per box. **Splits** lower it: each box's points are cut by a plane across one of the
   box's axes (at 7 positions, every axis), the cut with the smallest summed volume of the
   two new boxes wins, and it is kept if it saves more than `box_cost` (relative to the
   mesh's own volume), up to `max_boxes` boxes. A straight part stays one box; a bent or
   L-shaped one splits where its box is mostly air. A box holds the convex hull of its
   points, so a cut whose halves' hulls already hold more than a saving allows is not
   fitted (the same boxes in two thirds of the time).
3. **Assignment and refit** (the paper's last step, repeated): every sample goes to its
   nearest box (signed distance: the box it lies deepest inside), each box becomes the
   minimum oriented bounding box of its samples.

A box's density is that of the part it covers most, by volume (on the parts' voxels).
Offline NumPy and trimesh (dataset ground truth), not jitted.
"""

from __future__ import annotations

import jax
import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from ppdjax import primitives
from ppdjax.conventions import NUM_SLOTS
from ppdjax.dataset.meshes import check_solid, normalize, surface_samples, voxelize_parts

SAMPLES = 8_000  # surface samples the boxes are fitted to (about 0.7 s per tool)
BOX_COST = 0.15  # a split must save this fraction of the mesh's volume (measured on tools)
REFITS = 4  # rounds of nearest-box assignment and refit
CUTS = np.linspace(0.2, 0.8, 7)  # split planes, as fractions along a box's axis
MIN_POINTS = 8  # a box needs this many samples (a thinner piece is not split off)
MAX_PARTS = 64  # parts merged into boxes at most
NEIGHBOURS = 4  # the nearest groups a group may merge with


def _obb(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(centre (3,), rotation (3, 3) proper, half sizes (3,)) of the minimum oriented
  bounding box of (n, 3) points."""
  if len(points) < 4 or np.linalg.matrix_rank(points - points.mean(0), tol=1e-9) < 3:
    lo, hi = points.min(0), points.max(0)  # flat or tiny: the axis-aligned box
    return (lo + hi) / 2, np.eye(3), np.maximum((hi - lo) / 2, 1e-4)
  to_origin, extents = trimesh.bounds.oriented_bounds(points)
  box = np.linalg.inv(to_origin)
  rotation = box[:3, :3]
  if np.linalg.det(rotation) < 0:
    rotation = rotation * np.array([1.0, 1.0, -1.0])
  return box[:3, 3], rotation, np.maximum(np.asarray(extents) / 2, 1e-4)


def _volume(box) -> float:
  return float(8.0 * np.prod(box[2]))


def _signed_distance(points: np.ndarray, box) -> np.ndarray:
  """(n,) distance from each point to the box: negative inside (minus the depth)."""
  centre, rotation, half = box
  q = np.abs((points - centre) @ rotation) - half
  outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
  return outside + np.minimum(q.max(-1), 0.0)


def _hull_volume(points: np.ndarray) -> float:
  """The volume of the points' convex hull (0 if they are flat): no box around them holds
  less."""
  try:
    return float(ConvexHull(points).volume)
  except QhullError:
    return 0.0


def _best_split(points: np.ndarray, box, most: float = np.inf):
  """(volume of the two boxes, (points a, points b)) of the best plane cut, or None.

  With a finite `most`, the halves' convex hulls bound each cut's boxes from below (a box
  holds its points' hull): a cut whose bound exceeds `most`, or the best boxes fitted so
  far, cannot win and is not fitted; cuts are fitted in the order of their bounds. The
  winner is the one fitting every cut finds whenever its boxes hold at most `most`
  (ties go to the earlier cut, axis by axis as in CUTS); otherwise no cut is that good."""
  centre, rotation, half = box
  local = (points - centre) @ rotation
  cuts = []  # (lower bound, order, side)
  for axis in range(3):
    for f in CUTS:
      side = local[:, axis] < (f * 2 - 1) * half[axis]
      if side.sum() < MIN_POINTS or (~side).sum() < MIN_POINTS:
        continue
      bound = (_hull_volume(points[side]) + _hull_volume(points[~side])
               if most < np.inf else 0.0)
      if bound <= most * (1 + 1e-9):
        cuts.append((bound, len(cuts), side))
  best = None  # (volume, order, (points a, points b))
  for bound, order, side in sorted(cuts, key=lambda c: c[:2]):
    if best is not None and bound > best[0] * (1 + 1e-9):
      break  # every cut left holds more than the best already
    volume = _volume(_obb(points[side])) + _volume(_obb(points[~side]))
    if best is None or (volume, order) < best[:2]:
      best = (volume, order, (points[side], points[~side]))
  return None if best is None else (best[0], best[2])


def _merge_parts(groups: list[np.ndarray], max_boxes: int) -> list[np.ndarray]:
  """Merges point groups pairwise (least added box volume first) down to `max_boxes`.
  Only each group's NEIGHBOURS nearest groups (by centroid) are candidates, each pair
  fitted once: about 2·NEIGHBOURS box fits per part, not one per pair of parts per merge
  (30 parts took minutes); the cheapest merge joins near groups anyway."""
  groups = dict(enumerate(groups))
  volume = {i: _volume(_obb(g)) for i, g in groups.items()}
  cost = {}

  def add_pairs(i):
    others = [k for k in groups if k != i]
    near = sorted(others, key=lambda k: np.linalg.norm(groups[k].mean(0) - groups[i].mean(0)))
    for k in near[:NEIGHBOURS]:
      pair = (min(i, k), max(i, k))
      if pair not in cost:
        both = _volume(_obb(np.concatenate([groups[pair[0]], groups[pair[1]]])))
        cost[pair] = both - volume[i] - volume[k]

  for i in list(groups):
    add_pairs(i)
  fresh = len(groups)
  while len(groups) > max_boxes:
    i, j = min(cost, key=lambda pair: (cost[pair], pair))
    groups[fresh] = np.concatenate([groups.pop(i), groups.pop(j)])
    volume[fresh] = _volume(_obb(groups[fresh]))
    cost = {pair: c for pair, c in cost.items() if i not in pair and j not in pair}
    add_pairs(fresh)
    fresh += 1
  return list(groups.values())


def fit_point_boxes(points: np.ndarray, part: np.ndarray, mesh_volume: float,
                    max_boxes: int = NUM_SLOTS, box_cost: float = BOX_COST,
                    prune: bool = True) -> list:
  """Boxes (centre, rotation, half sizes) fitted to surface samples labelled by part.
  `prune`: skip the cuts that cannot save `box_cost` (the same boxes; False fits every cut,
  the peer of experiments/benchmarks/bench_tool_boxes.py)."""
  groups = [points[part == i] for i in np.unique(part)]
  groups = _merge_parts([g for g in groups if len(g)], max_boxes)
  least = box_cost * mesh_volume  # the saving a split must make
  while len(groups) < max_boxes:
    # a group whose cuts cannot save `least` offers none: the kept split is the same
    boxes = [_obb(g) for g in groups]
    volumes = [_volume(b) for b in boxes]
    trials = [(k, _best_split(g, boxes[k], most=volumes[k] - least if prune else np.inf))
              for k, g in enumerate(groups)]
    gains = [(volumes[k] - split[0], k, split[1]) for k, split in trials if split is not None]
    if not gains:
      break
    gain, k, (a, b) = max(gains, key=lambda g: g[0])
    if gain < least:
      break
    groups[k:k + 1] = [a, b]
  boxes = [_obb(g) for g in groups]
  for _ in range(REFITS):  # the paper's refinement: nearest box, then its minimum box
    owner = np.argmin(np.stack([_signed_distance(points, b) for b in boxes]), 0)
    kept = [k for k in range(len(boxes)) if (owner == k).sum() >= MIN_POINTS]
    boxes = [_obb(points[owner == k]) for k in kept]
  return boxes


def _part_volumes_in_box(box, per_part: np.ndarray) -> np.ndarray:
  """(parts,) how many of each part's voxel centres fall inside the box."""
  r = per_part.shape[-1]
  centres = (np.stack(np.nonzero(np.ones((r,) * 3, bool)), -1) + 0.5) / r - 0.5
  inside = _signed_distance(centres, box) <= 0.5 / r
  return per_part.reshape(len(per_part), -1)[:, inside].sum(-1)


# one compiled call per tool (an unjitted vmap traced itself again on every call: ~13 ms)
_mats_to_quats = jax.jit(jax.vmap(primitives.mat_to_quat))


def boxes_of_parts(parts, densities, max_boxes: int = NUM_SLOTS, *,
                   box_cost: float = BOX_COST, num_slots: int = NUM_SLOTS
                   ) -> tuple[primitives.Primitives, np.ndarray]:
  """(Primitives (num_slots,), owner (num_slots,) int): boxes of parts already in the
  normalised frame, bottom to top, each with the density of the part it covers most by
  volume (that part's index in `owner`; -1 for padded slots)."""
  points, part = surface_samples(parts, SAMPLES)
  volume = sum(abs(p.volume) for p in parts)
  boxes = fit_point_boxes(points, part, volume, max_boxes, box_cost)
  _, per_part = voxelize_parts(parts)
  owner = [int(np.argmax(_part_volumes_in_box(b, per_part))) for b in boxes]
  prims, order = as_primitives(boxes, [densities[o] for o in owner], num_slots)
  return prims, np.asarray(owner + [-1] * (num_slots - len(boxes)))[order]


def as_primitives(boxes, densities, num_slots: int = NUM_SLOTS
                  ) -> tuple[primitives.Primitives, np.ndarray]:
  """(Primitives (num_slots,) numpy, bottom to top and canonical; the order: slot i holds
  box order[i], padded slots past len(boxes)) of boxes (centre, rotation, half sizes) with
  a density each."""
  k, pad = len(boxes), num_slots - len(boxes)
  rotation = np.stack([b[1] for b in boxes] + [np.eye(3)] * pad)
  prims = primitives.Primitives(
      half_size=np.stack([b[2] for b in boxes] + [np.full(3, 0.05)] * pad).astype(np.float32),
      pos=np.stack([b[0] for b in boxes] + [np.zeros(3)] * pad).astype(np.float32),
      quat=np.asarray(_mats_to_quats(rotation.astype(np.float32))),
      density=np.asarray(list(densities) + [1000.0] * pad, np.float32),
      valid=np.arange(num_slots) < k)
  order = np.asarray(primitives.bottom_to_top_order(prims))
  prims = primitives.canonical_boxes(prims)
  prims = primitives.Primitives(*[np.asarray(getattr(prims, f))[order]
                                  for f in primitives.FIELDS])
  return prims, order


def primitives_from_mesh(mesh, max_boxes: int = NUM_SLOTS, densities=None, *,
                         box_cost: float = BOX_COST, num_slots: int = NUM_SLOTS
                         ) -> tuple[primitives.Primitives, np.ndarray]:
  """(Primitives (num_slots,), 4x4 transform): ground-truth boxes of a mesh.

  Args:
    mesh: a trimesh.Trimesh (parts: its connected components, vertices merged by position),
      a trimesh.Scene (parts: its meshes) or a list of parts, in any frame; it is
      normalised first (`meshes.normalize`). Parts must be solid and apart
      (`meshes.check_solid`), at most MAX_PARTS.
    max_boxes: at most this many boxes (1 to num_slots).
    densities: (parts,) kg/m^3, finite and > 0, one per part (default 1,000): each box
      takes that of the part it covers most by volume.
    box_cost: a split must save this fraction of the mesh's volume in box volume.
    num_slots: K of the returned Primitives (padded with invalid slots).

  Returns:
    the boxes in the normalised object frame, bottom to top, and the transform from the
    mesh's coordinates to that frame.
  """
  if not isinstance(max_boxes, (int, np.integer)) or not 1 <= max_boxes <= num_slots:
    raise ValueError(f"max_boxes must be an int in [1, {num_slots}], got {max_boxes!r}")
  if not np.isfinite(box_cost) or box_cost < 0:
    raise ValueError(f"box_cost must be finite and >= 0, got {box_cost!r}")
  parts, transform = normalize(mesh)
  if len(parts) > MAX_PARTS:
    raise ValueError(f"the mesh has {len(parts)} parts; at most {MAX_PARTS} are merged into "
                     f"{max_boxes} boxes (join parts first, e.g. trimesh.util.concatenate "
                     "of the small ones)")
  parts = check_solid(parts, [f"part{i}" for i in range(len(parts))], "the mesh")
  densities = (np.full(len(parts), 1000.0) if densities is None
               else np.asarray(densities, np.float64).reshape(-1))
  if densities.shape != (len(parts),):
    raise ValueError(f"densities must give each of the {len(parts)} parts one, got "
                     f"{densities.shape[0]}")
  if not np.all(np.isfinite(densities) & (densities > 0)):
    raise ValueError(f"densities must be finite and > 0 kg/m^3, got {densities.tolist()}")
  prims, _ = boxes_of_parts(parts, densities, max_boxes, box_cost=box_cost,
                            num_slots=num_slots)
  return prims, transform
