"""A user's mesh file as an object: parts, their materials and densities, the object frame.

`load_object` reads OBJ/STL/PLY/GLB (anything trimesh reads). Parts are the file's
groups (a scene's geometries, e.g. OBJ objects or GLB nodes), or, for a single mesh, its
connected components, with vertices merged by position first (texture seams split them:
`meshes.welded`). Every part must be a closed surface (its volume, mass and inertia are
defined), solid (no cavity inside another part) and apart from the others (no overlap:
`meshes.check_solid`); the object is brought into the normalised frame
(`meshes.normalize`).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import trimesh

from ppdjax.conventions import MAX_DENSITY, MIN_DENSITY, NUM_SLOTS, density_to_slot
from ppdjax.dataset.materials import ALL_MATERIAL_NAMES, material_slots
from ppdjax.dataset.meshes import check_solid, components, normalize, scene_parts
from ppdjax.dataset.tools import Tool

DEFAULT_MATERIAL = "wood"  # when neither materials nor densities are given (warned)


def _read_parts(path: str) -> tuple[list[trimesh.Trimesh], list[str]]:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no mesh file at {path!r}")
  try:
    loaded = trimesh.load(path)
  except Exception as e:  # trimesh raises many kinds for a corrupt or unknown file
    raise ValueError(f"cannot read {path!r} as a mesh ({type(e).__name__}: {e})") from e
  if isinstance(loaded, trimesh.Scene):
    parts, names = scene_parts(loaded)
  elif isinstance(loaded, trimesh.Trimesh):
    parts = components(loaded) if len(loaded.faces) else []
    names = [f"part{i}" for i in range(len(parts))] if len(parts) > 1 else ["part0"]
  else:
    raise ValueError(f"{path!r} holds no triangle mesh (got a {type(loaded).__name__})")
  if not parts:
    raise ValueError(f"{path!r} holds no triangles")
  return parts, names


def _per_part(value, names: list[str], what: str) -> list:
  """A value per part from a mapping by part name, a sequence in part order, or a scalar."""
  if isinstance(value, Mapping):
    unknown = sorted(set(value) - set(names))
    if unknown:
      raise ValueError(f"{what} names parts {unknown} that the object does not have; its "
                       f"parts are {names}")
    missing = [n for n in names if n not in value]
    if missing:
      raise ValueError(f"{what} gives no value for parts {missing} (parts: {names})")
    return [value[n] for n in names]
  if isinstance(value, (str, int, float, np.number)):
    return [value] * len(names)
  if isinstance(value, Sequence) or isinstance(value, np.ndarray):
    if len(value) != len(names):
      raise ValueError(f"{what} has {len(value)} values for {len(names)} parts ({names})")
    return list(value)
  raise ValueError(f"{what} must be a mapping by part name, a sequence or one value")


def typical_slot(material: str) -> int:
  """The median density slot of a material (e.g. wood 500, metal 7,800 kg/m^3)."""
  slots = material_slots(material)
  return int(slots[len(slots) // 2])


def load_object(path: str, part_materials=None, part_densities=None, upright: bool = False
                ) -> tuple[Tool, np.ndarray]:
  """(the object, 4x4 transform from the file's coordinates to the normalised frame).

  Args:
    path: an OBJ/STL/PLY/GLB (or other trimesh-readable) file.
    part_materials: a material per part (of `materials.ALL_MATERIAL_NAMES`: the paper's
      five, or pine, aluminium, steel, copper): a mapping by part name, a sequence in part
      order, or one name for all. Names are the file's
      groups, or part0, part1, ... (connected components, in trimesh's order).
    part_densities: kg/m^3 per part, the same forms; overrides the materials' typical
      densities (rounded to the 100 kg/m^3 density slots). With neither, every part is
      wood (with a warning).
    upright: the file's z axis stays up (a tower, normalised as the block towers are);
      else the object is turned onto its principal axes (the tools' frame).

  Returns:
    a `tools.Tool` (category "user") whose parts are in the normalised object frame, and
    the transform. Raises FileNotFoundError or ValueError naming the problem: an
    unreadable file, no triangles, a part that is not closed (volume undefined), zero
    volume, a cavity (a closed shell facing inward inside another part), overlapping
    parts, more parts than the NUM_SLOTS boxes, an unknown material or part name, a
    density outside [100, 10,000] kg/m^3.
  """
  parts, names = _read_parts(path)
  if len(parts) > NUM_SLOTS:
    raise ValueError(f"{path!r} has {len(parts)} parts; at most {NUM_SLOTS} fit the "
                     f"{NUM_SLOTS} boxes (join parts in the file, or group them)")
  for part, name in zip(parts, names):
    if not part.is_watertight:
      raise ValueError(f"part {name!r} of {path!r} is not a closed surface, so its volume "
                       "(mass, inertia) is undefined; close its holes first")
    if abs(part.volume) <= 1e-12 * max(part.extents.max(), 1e-12) ** 3:
      raise ValueError(f"part {name!r} of {path!r} has zero volume")
  if part_materials is None and part_densities is None:
    warnings.warn(f"no materials or densities given for {path!r}: every part is taken as "
                  f"{DEFAULT_MATERIAL}", stacklevel=2)
    part_materials = DEFAULT_MATERIAL
  materials = (_per_part(part_materials, names, "part_materials")
               if part_materials is not None else [DEFAULT_MATERIAL] * len(parts))
  for m in materials:
    if m not in ALL_MATERIAL_NAMES:
      raise ValueError(f"unknown material {m!r}; expected one of {ALL_MATERIAL_NAMES}")
  if part_densities is None:
    slots = [typical_slot(m) for m in materials]
  else:
    densities = np.asarray(_per_part(part_densities, names, "part_densities"), np.float64)
    bad = ~np.isfinite(densities) | (densities < MIN_DENSITY) | (densities > MAX_DENSITY)
    if bad.any():
      raise ValueError(f"part_densities must lie in [{MIN_DENSITY:g}, {MAX_DENSITY:g}] "
                       f"kg/m^3; got {densities[bad].tolist()} for "
                       f"{[n for n, b in zip(names, bad) if b]}")
    slots = [int(s) for s in density_to_slot(densities)]
  normalised, transform = normalize(parts, upright=upright)
  normalised = check_solid(normalised, names, repr(path))  # inward shells turned outward
  return Tool("user", tuple(normalised), tuple(names), tuple(str(m) for m in materials),
              tuple(slots)), transform
