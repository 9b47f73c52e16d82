"""Procedural daily-life tools (paper Sec. 5.2): meshes built from parts, each of a material.

The paper used 204 tools from 3D Warehouse, which cannot be downloaded here; ppdjax makes
its own. A tool is 1-3 watertight parts (trimesh primitives, tapered or bent so that boxes
only approximate them) in one of `CATEGORIES`, with random proportions; each part carries
one of the paper's five materials (Table 1) and a density slot drawn from its range
(metal heads and blades, wooden or ceramic handles). Parts touch but never overlap, so
their volumes, masses and inertias add up. Deterministic from (seed, index). Sizes are in
metres before normalisation (`ppdjax.dataset.meshes.normalize`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from ppdjax.conventions import slot_to_density
from ppdjax.dataset.materials import material_slots

CATEGORIES = ("hammer", "mallet", "axe", "screwdriver", "wrench", "spatula", "knife", "saw")
HANDLE_MATERIALS = ("wood", "ceramic")  # "plastic-like" handles: the paper has no plastic


@dataclasses.dataclass(frozen=True)
class Tool:
  """One tool: parts in the tool's frame (metres), with their names and materials.

  Attributes:
    category: one of CATEGORIES.
    parts: watertight trimesh meshes that touch but do not overlap.
    names: a name per part ("handle", "head", ...).
    materials: a material per part (keys of `materials.MATERIALS`).
    slots: a 0-based density slot per part, within its material's range.
  """

  category: str
  parts: tuple[trimesh.Trimesh, ...]
  names: tuple[str, ...]
  materials: tuple[str, ...]
  slots: tuple[int, ...]

  @property
  def densities(self) -> np.ndarray:
    """(parts,) kg/m^3."""
    return np.asarray([slot_to_density(s) for s in self.slots], np.float64)


# --- shaping parts --------------------------------------------------------------------------

def _cylinder(radius: float, length: float, sections: int = 24) -> trimesh.Trimesh:
  """A cylinder along z from z = 0 to z = length."""
  mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
  mesh.apply_translation([0.0, 0.0, length / 2])
  return mesh


def _box(extents, centre) -> trimesh.Trimesh:
  mesh = trimesh.creation.box(extents=extents)
  mesh.apply_translation(centre)
  return mesh


def _taper(mesh: trimesh.Trimesh, axis: int, ratio, about=None) -> trimesh.Trimesh:
  """Scales the cross-section linearly along `axis`, from 1 at its low end to `ratio`
  (a scalar, or one factor per axis) at its high end, about `about` (default: the
  bounding box's centre line)."""
  v = mesh.vertices.copy()
  lo, hi = v[:, axis].min(), v[:, axis].max()
  t = (v[:, axis] - lo) / max(hi - lo, 1e-12)
  centre = mesh.bounds.mean(0) if about is None else np.asarray(about, float)
  factor = 1 + (np.broadcast_to(np.asarray(ratio, float), (3,)) - 1) * t[:, None]
  factor[:, axis] = 1.0
  mesh.vertices = centre + (v - centre) * factor
  return mesh


def _bend(mesh: trimesh.Trimesh, axis: int, towards: int, amount: float) -> trimesh.Trimesh:
  """Moves vertices along `towards` by amount * t^2, t in [0, 1] along `axis` (a bow)."""
  for _ in range(3):  # midpoint subdivision keeps the mesh watertight
    mesh = mesh.subdivide()
  v = mesh.vertices.copy()
  lo, hi = v[:, axis].min(), v[:, axis].max()
  t = (v[:, axis] - lo) / max(hi - lo, 1e-12)
  v[:, towards] += amount * t ** 2
  mesh.vertices = v
  return mesh


def _handle(rng, length, radius) -> trimesh.Trimesh:
  """A round handle along z from 0 to length, a little narrower at the top."""
  return _taper(_cylinder(radius, length), 2, rng.uniform(0.75, 1.0))


# --- categories: each returns [(name, mesh, material), ...] -----------------------------------

def _hammer(rng):
  length, radius = rng.uniform(0.25, 0.35), rng.uniform(0.012, 0.018)
  hx, hy, hz = rng.uniform(0.09, 0.14), rng.uniform(0.022, 0.032), rng.uniform(0.022, 0.032)
  head = _taper(_box((hx, hy, hz), (rng.uniform(-0.2, 0.2) * hx, 0, length + hz / 2)),
                0, (1.0, rng.uniform(0.5, 1.0), 1.0))  # a claw end narrower than the face
  return [("handle", _handle(rng, length, radius), rng.choice(HANDLE_MATERIALS)),
          ("head", head, "metal")]


def _mallet(rng):
  length, radius = rng.uniform(0.22, 0.32), rng.uniform(0.012, 0.016)
  head_r, head_l = rng.uniform(0.03, 0.05), rng.uniform(0.08, 0.14)
  head = _cylinder(head_r, head_l)
  head.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
  head.apply_translation([-head_l / 2, 0, length + head_r])
  return [("handle", _handle(rng, length, radius), "wood"),
          ("head", head, rng.choice(["wood", "stone"]))]


def _axe(rng):
  length, radius = rng.uniform(0.35, 0.6), rng.uniform(0.014, 0.02)
  handle = _bend(_handle(rng, length, radius), 2, 0, rng.uniform(-0.04, 0.04))
  top = handle.vertices[handle.vertices[:, 2] > length - 1e-6].mean(0)
  hx, hy, hz = rng.uniform(0.08, 0.13), rng.uniform(0.012, 0.02), rng.uniform(0.05, 0.09)
  head = _box((hx, hy, hz), (top[0] + hx / 2 - 0.02, top[1], length + hz / 2))
  head = _taper(head, 0, (1.0, rng.uniform(0.1, 0.25), 1.0))  # a wedge, thin at the edge
  return [("handle", handle, "wood"), ("head", head, "metal")]


def _screwdriver(rng):
  grip_l, grip_r = rng.uniform(0.08, 0.12), rng.uniform(0.012, 0.02)
  shaft_l, shaft_r = rng.uniform(0.08, 0.16), rng.uniform(0.003, 0.005)
  grip = _taper(_cylinder(grip_r, grip_l, 8), 2, rng.uniform(0.7, 1.0))  # a fluted grip
  shaft = _cylinder(shaft_r, shaft_l)
  shaft.apply_translation([0, 0, grip_l])
  tip_l = rng.uniform(0.01, 0.02)
  tip = _taper(_box((2 * shaft_r, 2 * shaft_r, tip_l), (0, 0, grip_l + shaft_l + tip_l / 2)),
               2, (1.3, 0.3, 1.0))
  return [("handle", grip, rng.choice(HANDLE_MATERIALS)), ("shaft", shaft, "metal"),
          ("tip", tip, "metal")]


def _wrench(rng):
  length, width = rng.uniform(0.15, 0.25), rng.uniform(0.012, 0.02)
  thick = rng.uniform(0.005, 0.008)
  bar = _taper(_box((length, width, thick), (0, 0, 0)), 0, (1.0, rng.uniform(0.6, 1.0), 1.0))
  parts = [("bar", bar, "metal")]
  for side, name in ((-1, "small end"), (1, "large end")):
    size = width * rng.uniform(1.8, 2.6) * (1.2 if side > 0 else 1.0)
    parts.append((name, _box((size, size, thick), (side * (length + size) / 2, 0, 0)), "metal"))
  return parts


def _spatula(rng):
  length, radius = rng.uniform(0.15, 0.22), rng.uniform(0.008, 0.013)
  bw, bl, bt = rng.uniform(0.05, 0.08), rng.uniform(0.08, 0.12), rng.uniform(0.002, 0.004)
  blade = _taper(_box((bw, bt, bl), (0, 0, length + bl / 2)), 2, (rng.uniform(1.0, 1.3), 1, 1))
  blade = _bend(blade, 2, 1, rng.uniform(-0.02, 0.02))
  return [("handle", _handle(rng, length, radius), rng.choice(HANDLE_MATERIALS)),
          ("blade", blade, "metal")]


def _knife(rng):
  hl, hw, ht = rng.uniform(0.09, 0.13), rng.uniform(0.018, 0.026), rng.uniform(0.012, 0.018)
  bl, bw, bt = rng.uniform(0.1, 0.2), rng.uniform(0.02, 0.04), rng.uniform(0.0015, 0.003)
  blade = _taper(_box((bl, bw, bt), (hl + bl / 2, bw / 2 - hw / 2, 0)), 0,
                 (1.0, rng.uniform(0.1, 0.3), 1.0), about=(0, -hw / 2, 0))  # a point at the tip
  return [("handle", _box((hl, hw, ht), (hl / 2, 0, 0)), rng.choice(HANDLE_MATERIALS)),
          ("blade", blade, "metal")]


def _saw(rng):
  hl, hw, ht = rng.uniform(0.1, 0.14), rng.uniform(0.07, 0.1), rng.uniform(0.02, 0.03)
  bl, bw, bt = rng.uniform(0.25, 0.45), rng.uniform(0.06, 0.1), rng.uniform(0.001, 0.002)
  blade = _taper(_box((bl, bw, bt), (hl + bl / 2, 0, 0)), 0, (1.0, rng.uniform(0.4, 0.7), 1.0),
                 about=(0, -bw / 2, 0))
  return [("handle", _box((hl, hw, ht), (hl / 2, 0, 0)), "wood"), ("blade", blade, "metal")]


_BUILDERS = {"hammer": _hammer, "mallet": _mallet, "axe": _axe, "screwdriver": _screwdriver,
             "wrench": _wrench, "spatula": _spatula, "knife": _knife, "saw": _saw}


def sample_tool(seed: int, index: int, category: str | None = None) -> Tool:
  """Tool `index` of `seed` (a category drawn uniformly unless given)."""
  rng = np.random.default_rng([seed, index])
  if category is None:
    category = CATEGORIES[rng.integers(len(CATEGORIES))]
  if category not in _BUILDERS:
    raise ValueError(f"unknown tool category {category!r}; expected one of {CATEGORIES}")
  names, parts, materials = zip(*_BUILDERS[category](rng))
  slots = tuple(int(rng.choice(material_slots(str(m)))) for m in materials)
  return Tool(category, tuple(parts), tuple(names), tuple(str(m) for m in materials), slots)


def with_new_slots(tool: Tool, rng: np.random.Generator) -> Tool:
  """The same tool (geometry, materials) with each part's slot drawn again within its
  material's range: another density configuration, as a tower's configurations are."""
  slots = tuple(int(rng.choice(material_slots(m))) for m in tool.materials)
  return dataclasses.replace(tool, slots=slots)


def sample_tools(seed: int, count: int) -> list[Tool]:
  """`count` tools of `seed`, deterministic."""
  return [sample_tool(seed, i) for i in range(count)]
