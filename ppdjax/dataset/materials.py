"""The paper's materials (Table 1) as density-slot ranges, and their procedural textures."""

from __future__ import annotations

import functools

import numpy as np

# Inclusive slot ranges in units of 100 kg/m^3 (1-based, as in the paper's table).
MATERIALS: dict[str, tuple[tuple[int, int], ...]] = {
    "wood": ((1, 10),),
    "brick": ((11, 20),),
    "stone": ((21, 30),),
    "ceramic": ((31, 60),),
    "metal": ((21, 35), (71, 100)),
}
MATERIAL_NAMES = tuple(MATERIALS)

# The blocks of the paper's real towers (Sec. 5.3: pine, steel, aluminium, copper), each of
# one density: the real one (500, 7850, 2700, 8960 kg/m^3) rounded to a slot (steel's
# 7,850 half-way up to 7,900; `density_to_slot(7850)` rounds half to even, to 7,800).
REAL_MATERIALS: dict[str, int] = {"pine": 5, "aluminium": 27, "steel": 79, "copper": 90}
REAL_MATERIAL_NAMES = tuple(REAL_MATERIALS)
# A dataset's material ids index this tuple (-1 pads): the paper's five, then the real four.
ALL_MATERIAL_NAMES = MATERIAL_NAMES + REAL_MATERIAL_NAMES


# What a block shows (`data.look`). "material": its material's texture. The look-alike
# towers' (the paper's Fig. 5: objects that look alike can differ in physics): "painted",
# one paint on every block whatever its material, and "alike_metals", steel with
# aluminium's brushed finish (two materials, one look).
LOOKS = ("material", "painted", "alike_metals")
# Texture families by id: the materials' (same ids, same textures), then the paint.
LOOK_NAMES = ALL_MATERIAL_NAMES + ("paint",)


def look_ids(material_ids, look: str) -> np.ndarray:
  """Texture ids (`LOOK_NAMES`) that blocks of `material_ids` (`ALL_MATERIAL_NAMES` ids,
  -1 padding, any shape) show under `look` (`LOOKS`); padding stays -1."""
  if look not in LOOKS:
    raise ValueError(f"data.look must be one of {LOOKS}, got {look!r}")
  ids = np.asarray(material_ids)
  if look == "painted":
    return np.where(ids >= 0, LOOK_NAMES.index("paint"), -1)
  if look == "alike_metals":
    return np.where(ids == ALL_MATERIAL_NAMES.index("steel"),
                    ALL_MATERIAL_NAMES.index("aluminium"), ids)
  return ids


def material_slots(name: str) -> np.ndarray:
  """0-based density slots a material may take."""
  if name in REAL_MATERIALS:
    return np.array([REAL_MATERIALS[name] - 1])
  if name not in MATERIALS:
    raise ValueError(f"unknown material {name!r}; expected one of {ALL_MATERIAL_NAMES}")
  return np.concatenate([np.arange(lo - 1, hi) for lo, hi in MATERIALS[name]])


# --- procedural textures -------------------------------------------------------------------
# One family per material, randomised per block from a seed. A texture depends on the
# material and the seed only, never on the density: an image reveals the material and
# nothing about where the density lies within the material's range.

TEXTURE_SIZE = 64
TEXTURE_VARIANTS = 256  # the dataset draws texture seeds from this many per material


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
  """Smooth noise in [0, 1]: a random `cells` x `cells` grid, bilinearly upsampled."""
  grid = rng.random((cells + 1, cells + 1))
  t = np.linspace(0, cells, size, endpoint=False)
  i = t.astype(int)
  f = t - i
  f = f * f * (3 - 2 * f)
  rows = grid[i] * (1 - f)[:, None] + grid[i + 1] * f[:, None]
  return rows[:, i] * (1 - f)[None] + rows[:, i + 1] * f[None]


def _fractal(rng, size, octaves=(4, 8, 16)) -> np.ndarray:
  n = sum(_value_noise(rng, size, c) / (k + 1) for k, c in enumerate(octaves))
  return (n - n.min()) / (np.ptp(n) + 1e-9)


def _wood(rng, size):
  y, x = np.mgrid[0:size, 0:size] / size
  warp = _fractal(rng, size, (2, 4)) * rng.uniform(1.0, 2.5)
  rings = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.uniform(4, 9) * (y + 0.15 * x) + warp))
  base = np.array([0.55, 0.36, 0.18]) * rng.uniform(0.85, 1.15)
  dark = base * 0.55
  return base * (1 - rings[..., None] ** 3) + dark * rings[..., None] ** 3


def _brick(rng, size):
  rows = int(rng.integers(4, 7))
  h = size / rows
  y, x = np.mgrid[0:size, 0:size].astype(float)
  row = (y // h).astype(int)
  w = 2 * h * rng.uniform(0.9, 1.3)
  xs = x + (row % 2) * w / 2
  col = (xs // w).astype(int)
  mortar = ((y % h) < 1.5) | ((xs % w) < 1.5)
  jitter = rng.uniform(0.8, 1.15, (rows + 1, int(size / w) + 3))[row, col]
  base = np.array([0.62, 0.22, 0.14]) * rng.uniform(0.85, 1.1)
  img = base * jitter[..., None] * (0.85 + 0.15 * _fractal(rng, size)[..., None])
  return np.where(mortar[..., None], np.array([0.72, 0.70, 0.66]), img)


def _stone(rng, size):
  n = _fractal(rng, size, (3, 6, 12, 24))
  speck = rng.random((size, size)) < 0.04
  grey = 0.35 + 0.35 * n
  img = np.stack([grey, grey * 0.98, grey * 0.93], -1) * rng.uniform(0.85, 1.15)
  return np.where(speck[..., None], img * 0.6, img)


def _ceramic(rng, size):
  tint = np.array([0.93, 0.91, 0.86]) + rng.uniform(-0.06, 0.04, 3)
  glaze = 0.94 + 0.06 * _fractal(rng, size, (2, 3))
  crackle = _fractal(rng, size, (10, 20))
  lines = np.abs(crackle - 0.5) < 0.015
  img = tint * glaze[..., None]
  return np.where(lines[..., None], img * 0.8, img)


def _metal(rng, size, tint=(0.78, 0.80, 0.84)):
  streaks = rng.random(size)[:, None] * 0.6 + _value_noise(rng, size, 16) * 0.4
  shine = 0.45 + 0.3 * streaks + 0.15 * np.linspace(0, 1, size)[None, :]
  return shine[..., None] * np.asarray(tint) * rng.uniform(0.85, 1.1)


def _paint(rng, size):
  """A matte paint, one colour for every block (the seed varies only its fine grain)."""
  grain = 0.94 + 0.06 * _value_noise(rng, size, 32)
  return grain[..., None] * np.asarray([0.25, 0.42, 0.62])


def _pine(rng, size):
  return _wood(rng, size) * np.array([1.45, 1.6, 1.9])  # pale yellow softwood


_FAMILIES = {"wood": _wood, "brick": _brick, "stone": _stone, "ceramic": _ceramic,
             "metal": _metal, "pine": _pine,
             # brushed metals: aluminium light, steel darker and bluish, copper orange
             "aluminium": functools.partial(_metal, tint=(0.86, 0.87, 0.88)),
             "steel": functools.partial(_metal, tint=(0.58, 0.61, 0.66)),
             "copper": functools.partial(_metal, tint=(0.86, 0.52, 0.32)),
             "paint": _paint}


@functools.lru_cache(maxsize=len(LOOK_NAMES) * TEXTURE_VARIANTS)
def texture(material: str, seed: int, size: int = TEXTURE_SIZE) -> np.ndarray:
  """(size, size, 3) uint8 procedural texture of `material` (or another look of
  `LOOK_NAMES`), randomised by `seed` (cached; do not modify the returned array)."""
  if material not in _FAMILIES:
    raise ValueError(f"unknown material {material!r}; expected one of {LOOK_NAMES}")
  rng = np.random.default_rng([LOOK_NAMES.index(material), int(seed)])
  img = _FAMILIES[material](rng, size)
  return (np.clip(img, 0, 1) * 255).astype(np.uint8)
