"""Meshes into the project's frame: normalisation and exact voxels (the tools' inputs).

`normalize`: the paper's (ShapeNet's) normalisation. The surface's principal axes (its
area-weighted second moments, exact over the triangles) become x, y, z by decreasing
spread, so a tool lies flat on the ground (z up, its thinnest direction); each axis points
towards the side with more surface beyond the centre (positive third moment), making the
frame unique; then the bounding box is centred at the origin and the largest extent scaled
to 1 m (DESIGN.md). Where two or three spreads are equal (a cube, a square rod) any axes
of their plane are principal; those of the mesh's own largest faces are taken there, so
the object rests on a face (not on an edge, as arbitrary axes would leave it).

`welded`: a mesh exported with texture coordinates (Blender's OBJ, GLB) repeats a vertex
wherever a texture seam runs through it, so its faces do not share edges there; the parts
are read after merging vertices by position. `check_solid`: a part is solid material, so
a cavity (a closed shell facing inward inside another part) or two overlapping parts
would give the object the wrong mass; both are refused by name.

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


TIED = 1e-4  # spreads closer than this (relative to the largest) are equal: a symmetry
PARALLEL = 1e-6  # 1 - |cos| below which two face normals share a direction


def welded(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
  """A copy with vertices merged by position alone (texture coordinates and normals split
  them at seams), so that faces meeting there share their edges."""
  out = mesh.copy()
  out.merge_vertices(merge_tex=True, merge_norm=True)
  return out


def components(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
  """Connected components by shared edges once vertices are merged by position
  (`welded`), in the file's face order (scipy; no repair, so an open part stays open and
  is reported as such)."""
  mesh = welded(mesh)
  groups = trimesh.graph.connected_components(
      mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1, engine="scipy")
  groups = sorted(groups, key=lambda g: int(np.min(g)))
  return list(mesh.submesh(groups, append=False, repair=False))


def parts_of(mesh) -> list[trimesh.Trimesh]:
  """A list of part meshes: a Trimesh's connected components, a Scene's geometries (placed
as the scene places them), or the given parts."""
  if isinstance(mesh, trimesh.Trimesh):
    return components(mesh) or [mesh]
  if isinstance(mesh, trimesh.Scene):
    return scene_parts(mesh)[0]
  parts = list(mesh) if isinstance(mesh, (list, tuple)) else []
  if not parts or not all(isinstance(p, trimesh.Trimesh) for p in parts):
    raise ValueError("expected a trimesh.Trimesh, a trimesh.Scene or a non-empty list of "
                     f"trimesh.Trimesh parts, got {type(mesh).__name__}")
  return parts


def scene_parts(scene: trimesh.Scene) -> tuple[list[trimesh.Trimesh], list[str]]:
  """(parts, node names): each triangle mesh of a scene where the scene places it, in the
  file's order of geometries, its vertices merged by position (`welded`)."""
  parts, names = [], []
  order = {name: i for i, name in enumerate(scene.geometry)}
  nodes = sorted(scene.graph.nodes_geometry,
                 key=lambda n: (order.get(scene.graph[n][1], len(order)), str(n)))
  for node in nodes:
    transform, geometry = scene.graph[node]
    mesh = scene.geometry[geometry]
    if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces):
      parts.append(welded(mesh).apply_transform(transform))
      names.append(str(node))
  return parts, names


def surface_samples(parts, count: int, seed: int = 0):
  """(points (n, 3), part index (n,)) sampled uniformly by area over all parts."""
  union = trimesh.util.concatenate(parts)
  owner = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
  points, faces = trimesh.sample.sample_surface(union, count, seed=seed)
  return np.asarray(points), owner[faces]


def normalize(mesh, upright: bool = False) -> tuple[list[trimesh.Trimesh], np.ndarray]:
  """(parts in the normalised object frame, the 4x4 transform from the mesh's frame).

  Args:
    mesh: a trimesh.Trimesh (parts: its connected components) or a sequence of parts.
    upright: keep the mesh's own axes (its z up: a tower standing as it stands) and only
      centre and scale it, as the block towers are; else turn it onto its principal axes,
      the longest along x (the tools' convention).
  """
  parts = parts_of(mesh)
  if sum(p.area for p in parts) <= 0:
    raise ValueError("the mesh has no surface")
  rotate = np.eye(4)
  if not upright:
    rotate = _principal_frame(parts)
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


def _principal_frame(parts) -> np.ndarray:
  """The 4x4 transform onto the surface's principal axes about its centroid, the largest
  spread along x, each axis towards the surface's heavier tail, right-handed."""
  centre, cov = _surface_moments(parts)
  spreads, axes = np.linalg.eigh(cov)
  spreads, axes = spreads[::-1], axes[:, ::-1]  # largest spread first: x, y, z
  axes = _face_axes_where_tied(parts, spreads, axes)
  points, _ = surface_samples(parts, 50_000)
  skew = (((points - centre) @ axes) ** 3).mean(0)
  axes = axes * np.where(skew < 0, -1.0, 1.0)
  axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])  # right-handed
  rotate = np.eye(4)
  rotate[:3, :3] = axes.T
  rotate[:3, 3] = -axes.T @ centre
  return rotate


def _surface_moments(parts) -> tuple[np.ndarray, np.ndarray]:
  """(centroid (3,), covariance (3, 3)) of the surface, area-weighted, exact: over a
  triangle (a, b, c) of area A, the integral of x x^T is A/12 (a a^T + b b^T + c c^T +
  s s^T) with s = a + b + c."""
  tri = np.concatenate([np.asarray(p.triangles, np.float64) for p in parts])  # (F, 3, 3)
  area = np.concatenate([np.asarray(p.area_faces, np.float64) for p in parts])
  centre = np.einsum("f,fi->i", area, tri.sum(1)) / (3.0 * area.sum())
  tri = tri - centre
  s = tri.sum(1)
  second = np.einsum("f,fvi,fvj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, s, s)
  return centre, second / (12.0 * area.sum())


def _face_axes_where_tied(parts, spreads, axes) -> np.ndarray:
  """`axes` (3, 3 columns) with each group of equal spreads (`TIED`) turned to the
  directions of the mesh's largest faces within that group's plane or space: the normal
  with the most face area first, then the most area orthogonal to it. A group whose plane
  holds no face normal (a sphere's) keeps its axes."""
  normals = np.concatenate([np.asarray(p.face_normals, np.float64) for p in parts])
  area = np.concatenate([np.asarray(p.area_faces, np.float64) for p in parts])
  tied = np.abs(np.diff(spreads)) <= TIED * max(spreads[0], 1e-30)
  groups, start = [], 0
  for i in range(3):
    if i == 2 or not tied[i]:
      if i > start:
        groups.append(list(range(start, i + 1)))
      start = i + 1
  axes = axes.copy()
  for group in groups:
    basis = axes[:, group]
    inside = np.linalg.norm(normals @ basis, axis=1) > 1.0 - PARALLEL
    if not inside.any():
      continue
    direction, weight = _directions(normals[inside], area[inside])
    first = basis @ (basis.T @ direction[np.argmax(weight)])  # exactly in the group's span
    first = first / np.linalg.norm(first)
    chosen = [first]
    if len(group) == 3:
      across = np.abs(direction @ first) < PARALLEL
      second = (direction[across][np.argmax(weight[across])] if across.any()
                else _orthogonal(first))
      chosen.append(second)
    else:
      chosen.append(np.cross(np.cross(basis[:, 0], basis[:, 1]), first))
    if len(group) == 3:
      chosen.append(np.cross(chosen[0], chosen[1]))
    axes[:, group] = np.stack(chosen, 1)
  return axes


def _directions(normals, area) -> tuple[np.ndarray, np.ndarray]:
  """(unique directions (n, 3), their total face area (n,)): normals taken up to sign."""
  sign = np.where(np.take_along_axis(normals, np.argmax(np.abs(normals), 1)[:, None], 1) < 0,
                  -1.0, 1.0)
  key = np.round(normals * sign / np.sqrt(PARALLEL)).astype(np.int64)
  _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
  weight = np.bincount(inverse.reshape(-1), weights=area)
  direction = normals[first] * sign[first]
  return direction / np.linalg.norm(direction, axis=1, keepdims=True), weight


def _orthogonal(v) -> np.ndarray:
  other = np.eye(3)[np.argmin(np.abs(v))]
  w = np.cross(v, other)
  return w / np.linalg.norm(w)


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


OVERLAP = 0.05  # parts sharing more of the smaller one's interior voxels than this overlap


def check_solid(parts, names, source: str) -> list[trimesh.Trimesh]:
  """The parts (normalised frame) with closed shells that face inward turned outward.

  Raises ValueError naming the parts where a closed shell faces inward inside another part
  (a cavity: the object is hollow, and counting the shell as solid would add its volume to
  the mass instead of taking it away), or where two parts' interiors share more than
  `OVERLAP` of the smaller one's voxels (the overlap would be counted twice)."""
  _, filled = voxelize_parts(parts)
  size = filled.reshape(len(parts), -1).sum(-1)
  inward = [p.is_watertight and p.volume < 0 for p in parts]
  for i in np.flatnonzero(inward):
    for j in range(len(parts)):
      if j != i and size[i] and (filled[i] & filled[j]).sum() >= 0.5 * size[i]:
        raise ValueError(
            f"part {names[i]!r} of {source} is a closed shell facing inward inside part "
            f"{names[j]!r}: a cavity (a hollow object). Parts are solid here, so its mass "
            "would be wrong; fill the cavity (delete the inner shell) or split the walls "
            "into solid parts")
  interior = [ndimage.binary_erosion(g) for g in filled]
  for i in range(len(parts)):
    for j in range(i + 1, len(parts)):
      shared = int((interior[i] & interior[j]).sum())
      if shared > OVERLAP * min(size[i], size[j]):
        raise ValueError(
            f"parts {names[i]!r} and {names[j]!r} of {source} overlap (they share about "
            f"{100 * shared / min(size[i], size[j]):.0f}% of the smaller one's volume), so "
            "the overlap would be counted twice in the mass; cut one part back to where the "
            "other begins")
  out = []
  for p, flip in zip(parts, inward):
    if flip:
      p = p.copy()
      p.invert()
    out.append(p)
  return out
