"""Meshes into the project's frame: normalisation and exact voxels (the tools' inputs).

`normalize`: the paper's (ShapeNet's) normalisation. The surface's principal axes (PCA of
area-weighted surface samples) become x, y, z by decreasing spread, so a tool lies flat
on the ground (z up, its thinnest direction); each axis points towards the side with more
surface beyond the centre (positive third moment), making the frame unique; then the
bounding box is centred at the origin and the largest extent scaled to 1 m (DESIGN.md).

`voxelize_parts`: 32^3 occupancy as binvox computes it for the paper: a voxel is filled if
the surface passes through it or it lies inside (holes filled), per part and for the
union. The surface is found by dense samples, so a voxel it only grazes may stay empty.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage

from ppdjax.conventions import VOXEL_RESOLUTION as R

SURFACE_SAMPLES = 200_000  # about 20 per voxel face crossed: thin parts are not missed
VOXEL = 1.0 / R


def components(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
  """Connected components by shared edges, in the file's face order (scipy; no repair,
  so an open part stays open and is reported as such)."""
  groups = trimesh.graph.connected_components(
      mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1, engine="scipy")
  groups = sorted(groups, key=lambda g: int(np.min(g)))
  return list(mesh.submesh(groups, append=False, repair=False))


def parts_of(mesh) -> list[trimesh.Trimesh]:
  """A list of part meshes: a Trimesh's connected components, or the given parts."""
  if isinstance(mesh, trimesh.Trimesh):
    return components(mesh) or [mesh]
  parts = list(mesh)
  if not parts or not all(isinstance(p, trimesh.Trimesh) for p in parts):
    raise ValueError("expected a trimesh.Trimesh or a non-empty sequence of them")
  return parts


def surface_samples(parts, count: int, seed: int = 0):
  """(points (n, 3), part index (n,)) sampled uniformly by area over all parts."""
  union = trimesh.util.concatenate(parts)
  owner = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
  points, faces = trimesh.sample.sample_surface(union, count, seed=seed)
  return np.asarray(points), owner[faces]


def normalize(mesh) -> tuple[list[trimesh.Trimesh], np.ndarray]:
  """(parts in the normalised object frame, the 4x4 transform from the mesh's frame).

  Args:
    mesh: a trimesh.Trimesh (parts: its connected components) or a sequence of parts.
  """
  parts = parts_of(mesh)
  if sum(p.area for p in parts) <= 0:
    raise ValueError("the mesh has no surface")
  points, _ = surface_samples(parts, 50_000)
  centre = points.mean(0)
  evals, axes = np.linalg.eigh(np.cov((points - centre).T))
  axes = axes[:, ::-1]  # largest spread first: x, y, z
  skew = (((points - centre) @ axes) ** 3).mean(0)
  axes = axes * np.where(skew < 0, -1.0, 1.0)
  axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])  # right-handed
  rotate = np.eye(4)
  rotate[:3, :3] = axes.T
  rotate[:3, 3] = -axes.T @ centre
  turned = trimesh.util.concatenate(parts).copy()
  turned.apply_transform(rotate)
  lo, hi = turned.bounds
  extent = (hi - lo).max()
  if extent <= 0:
    raise ValueError("the mesh has zero extent")
  scale = np.diag([1 / extent] * 3 + [1.0])
  shift = np.eye(4)
  shift[:3, 3] = -(lo + hi) / 2
  transform = scale @ shift @ rotate
  out = []
  for p in parts:
    q = p.copy()
    q.apply_transform(transform)
    out.append(q)
  return out, transform


def voxelize_parts(parts) -> tuple[np.ndarray, np.ndarray]:
  """(union (32, 32, 32) bool, per part (parts, 32, 32, 32) bool) of normalised parts."""
  grids = []
  total = sum(p.area for p in parts)
  for i, p in enumerate(parts):
    count = max(1000, int(SURFACE_SAMPLES * p.area / total))
    points, _ = trimesh.sample.sample_surface(p, count, seed=i)
    grid = np.zeros((R, R, R), bool)
    index = np.clip(np.floor((np.asarray(points) + 0.5) / VOXEL).astype(int), 0, R - 1)
    grid[tuple(index.T)] = True
    grids.append(ndimage.binary_fill_holes(grid))
  grids = np.stack(grids)
  return grids.any(0), grids
