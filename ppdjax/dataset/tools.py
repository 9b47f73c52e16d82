"""Procedural daily-life tools (paper Sec. 5.2): meshes built from parts, each of a material.

The paper used 204 tools from 3D Warehouse, which cannot be downloaded here; ppdjax makes
its own. A tool is 1-3 watertight parts (trimesh primitives, tapered or bent so that boxes
only approximate them) in one of `CATEGORIES`, with random proportions; each part carries
one of the paper's five materials (Table 1) and a density slot drawn from its range. Parts
touch but never overlap, so their volumes, masses and inertias add up. Deterministic from
(seed, index). Sizes are in metres before normalisation (`ppdjax.dataset.meshes.normalize`).

Two labellings of the same geometry:
  * "category" (`sample_tool`, the datasets made before "plausible" existed): materials fixed
    by category (metal heads and blades, wooden or ceramic handles), a density slot per
    part, every part its own piece;
  * "plausible" (`sample_plausible_tool` = `with_plausible_materials` of the same tool, drawn
    from a separate stream, `MATERIAL_STREAM`): parts that are one physical piece share a
    material and a slot (`Tool.pieces`: a wrench's bar and ends, a screwdriver's shaft and
    tip), and each piece's material is drawn uniformly from its part's plausible set
    (`PLAUSIBLE_MATERIALS`). The meshes are bit-identical in both.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from ppdjax.conventions import slot_to_density
from ppdjax.dataset.materials import material_slots

CATEGORIES = ("hammer", "mallet", "axe", "screwdriver", "wrench", "spatula", "knife", "saw")
HANDLE_MATERIALS = ("wood", "ceramic")  # "plastic-like" handles: the paper has no plastic

# The "plausible" labelling: per category, its physical pieces (part names that are one piece
# of one material, so one density) and the materials a piece may be made of, each drawn
# uniformly. A handle may be wood, metal or plastic-like ("ceramic": Table 1 has no plastic),
# except where a metal one would be odd (a screwdriver's or saw's grip); heads and blades that
# take blows or hold an edge are metal, or stone or ceramic (a stone hammer or axe, a ceramic
# knife), a mallet's head is soft or heavy rather than metal, and a spatula's blade may be
# wooden or plastic-like. A wrench is forged in one piece; a screwdriver's shaft and tip are
# one rod. No tool is brick.
PLAUSIBLE_MATERIALS: dict[str, tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]] = {
    "hammer": ((("handle",), ("wood", "ceramic", "metal")), (("head",), ("metal", "stone"))),
    "mallet": ((("handle",), ("wood", "ceramic", "metal")),
               (("head",), ("wood", "stone", "ceramic"))),
    "axe": ((("handle",), ("wood", "ceramic", "metal")), (("head",), ("metal", "stone"))),
    "screwdriver": ((("handle",), ("wood", "ceramic")), (("shaft", "tip"), ("metal",))),
    "wrench": ((("bar", "small end", "large end"), ("metal",)),),
    "spatula": ((("handle",), ("wood", "ceramic", "metal")),
                (("blade",), ("metal", "wood", "ceramic"))),
    "knife": ((("handle",), ("wood", "ceramic", "metal")), (("blade",), ("metal", "ceramic"))),
    "saw": ((("handle",), ("wood", "ceramic")), (("blade",), ("metal",))),
}
# The third seed word of the plausible labels' stream, (seed, index, MATERIAL_STREAM): apart
# from the geometry's (seed, index) and the density configurations' (seed, index, c), c small,
# so that relabelling a tool changes neither its meshes nor the legacy draws.
MATERIAL_STREAM = 0x6D61746C  # "matl"


@dataclasses.dataclass(frozen=True)
class Tool:
  """One tool: parts in the tool's frame (metres), with their names and materials.

  Attributes:
    category: one of CATEGORIES.
    parts: watertight trimesh meshes that touch but do not overlap.
    names: a name per part ("handle", "head", ...).
    materials: a material per part (keys of `materials.MATERIALS`).
    slots: a 0-based density slot per part, within its material's range.
    pieces: the physical piece of each part, 0, 1, ... in order of first appearance; the
      parts of one piece share material and slot (default: every part its own piece).
  """

  category: str
  parts: tuple[trimesh.Trimesh, ...]
  names: tuple[str, ...]
  materials: tuple[str, ...]
  slots: tuple[int, ...]
  pieces: tuple[int, ...] = ()

  def __post_init__(self):
    pieces = tuple(int(p) for p in self.pieces) or tuple(range(len(self.parts)))
    object.__setattr__(self, "pieces", pieces)  # frozen: set once, here
    if len(pieces) != len(self.parts) or _first_appearance(pieces) != pieces:
      raise ValueError(f"pieces must give each of the {len(self.parts)} parts a piece "
                       f"0, 1, ... in order of first appearance, got {pieces}")
    for p in set(pieces):
      labels = {(self.materials[i], self.slots[i]) for i in range(len(pieces)) if pieces[i] == p}
      if len(labels) > 1:
        raise ValueError(f"the parts of piece {p} ({self.category}) must share one material "
                         f"and slot, got {sorted(labels)}")

  @property
  def densities(self) -> np.ndarray:
    """(parts,) kg/m^3."""
    return np.asarray([slot_to_density(s) for s in self.slots], np.float64)

  @property
  def num_pieces(self) -> int:
    return len(set(self.pieces))


def _first_appearance(labels) -> tuple[int, ...]:
  """`labels` renumbered 0, 1, ... in order of first appearance."""
  order: dict = {}
  return tuple(order.setdefault(x, len(order)) for x in labels)


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


def _piece_slots(pieces, materials, rng) -> tuple[int, ...]:
  """A slot per part: one drawn per piece, in piece order, uniformly within the piece's
  material's range, shared by its parts (one per part in part order where every part is its
  own piece: the draws from before pieces existed)."""
  material = {}
  for p, m in zip(pieces, materials):
    material.setdefault(p, m)
  drawn = [int(rng.choice(material_slots(material[p]))) for p in range(len(material))]
  return tuple(drawn[p] for p in pieces)


def with_new_slots(tool: Tool, rng: np.random.Generator) -> Tool:
  """The same tool (geometry, materials) with each piece's slot drawn again within its
  material's range: another density configuration, as a tower's configurations are."""
  return dataclasses.replace(tool, slots=_piece_slots(tool.pieces, tool.materials, rng))


def with_plausible_materials(tool: Tool, rng: np.random.Generator) -> Tool:
  """The same geometry labelled by `PLAUSIBLE_MATERIALS`: its real pieces, each piece's
  material drawn uniformly from its set, then each piece's slot uniformly within that
  material's range (all from `rng`), shared by the piece's parts."""
  if tool.category not in PLAUSIBLE_MATERIALS:
    raise ValueError(f"no plausible materials for tool category {tool.category!r}; expected "
                     f"one of {tuple(PLAUSIBLE_MATERIALS)}")
  table = PLAUSIBLE_MATERIALS[tool.category]
  piece_of = {name: k for k, (names, _) in enumerate(table) for name in names}
  unknown = [n for n in tool.names if n not in piece_of]
  if unknown:
    raise ValueError(f"{tool.category} parts {unknown} are not in PLAUSIBLE_MATERIALS")
  rows = [piece_of[n] for n in tool.names]
  pieces = _first_appearance(rows)
  choices = {p: table[r][1] for p, r in zip(pieces, rows)}
  drawn = [choices[p][int(rng.integers(len(choices[p])))] for p in range(len(choices))]
  materials = tuple(drawn[p] for p in pieces)
  return dataclasses.replace(tool, materials=materials, pieces=pieces,
                             slots=_piece_slots(pieces, materials, rng))


def sample_plausible_tool(seed: int, index: int, category: str | None = None) -> Tool:
  """`sample_tool(seed, index, category)` (the same meshes) under the "plausible" labels,
  drawn from (seed, index, MATERIAL_STREAM)."""
  return with_plausible_materials(sample_tool(seed, index, category),
                                  np.random.default_rng([seed, index, MATERIAL_STREAM]))


def part_thicknesses(parts) -> np.ndarray:
  """(parts,) the thinnest side of each part's minimum oriented bounding box (its units)."""
  return np.asarray([float(np.min(p.bounding_box_oriented.primitive.extents)) for p in parts])


def sample_tools(seed: int, count: int) -> list[Tool]:
  """`count` tools of `seed`, deterministic."""
  return [sample_tool(seed, i) for i in range(count)]
