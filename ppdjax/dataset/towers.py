"""Random block towers (paper Sec. 5.1): geometry, then material configurations.

A tower's geometry is sampled once; each of its configurations assigns every block one
of the five materials and a density drawn uniformly from that material's slots.

Size ranges (full extents before scaling; only ratios matter once the tower is scaled so
its largest extent is 1 m): footprints U(0.5, 1.5) on each side and heights U(0.3, 1.0).
Footprints wider than heights keep 2-5 block towers mostly standing at rest yet tall
enough to tip when pushed, and the 3:1 spread in each dimension keeps blocks visibly
different, so geometry alone does not reveal how mass is distributed.
"""

from __future__ import annotations

import numpy as np

from ppdjax.conventions import NUM_SLOTS, slot_to_density
from ppdjax.dataset import materials
from ppdjax.primitives import Primitives, corners, make, stack

WIDTH_RANGE = (0.5, 1.5)
HEIGHT_RANGE = (0.3, 1.0)
CONFIGS_PER_TOWER = 8


def sample_geometry(rng: np.random.Generator, num_blocks: int | None = None, *,
                    rotate: float = 0.0, size_noise: float = 0.0,
                    num_slots: int = NUM_SLOTS):
  """Block half sizes, centres and quaternions of one tower, scaled and centred.

  Block k+1 is centred at x ~ N(x_k, w_k / 4), y ~ N(y_k, d_k / 4) (w, d: the width and
  depth of block k) and rests on block k.

  Args:
    rng: numpy Generator.
    num_blocks: 2..num_slots, or None for uniform in that range.
    rotate: if > 0, each block turns by up to this angle (radians) about a random axis
      after stacking (the paper's noise for tool pretraining); blocks may then overlap.
    size_noise: if > 0, each extent is scaled by U(1 - size_noise, 1 + size_noise) after
      stacking.
    num_slots: K.

  Returns:
    (half_size (n, 3), pos (n, 3), quat (n, 4)) float64, in the object frame.
  """
  n = int(rng.integers(2, num_slots + 1)) if num_blocks is None else int(num_blocks)
  if not 1 <= n <= num_slots:
    raise ValueError(f"num_blocks must be in 1..{num_slots}, got {n}")
  if not 0 <= rotate <= np.pi or not 0 <= size_noise < 1:
    raise ValueError(f"rotate must be in [0, pi] and size_noise in [0, 1), got {rotate}, "
                     f"{size_noise}")
  size = np.column_stack([rng.uniform(*WIDTH_RANGE, n), rng.uniform(*WIDTH_RANGE, n),
                          rng.uniform(*HEIGHT_RANGE, n)])
  pos = np.zeros((n, 3))
  pos[0, 2] = size[0, 2] / 2
  for k in range(1, n):
    pos[k, 0] = rng.normal(pos[k - 1, 0], size[k - 1, 0] / 4)
    pos[k, 1] = rng.normal(pos[k - 1, 1], size[k - 1, 1] / 4)
    pos[k, 2] = pos[k - 1, 2] + (size[k - 1, 2] + size[k, 2]) / 2
  quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
  if size_noise > 0:
    size = size * rng.uniform(1 - size_noise, 1 + size_noise, size.shape)
  if rotate > 0:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, rotate, n)
    quat = np.column_stack([np.cos(angle / 2), axis * np.sin(angle / 2)[:, None]])
  # scale and centre on the bounding box of the (possibly rotated) blocks
  c = np.asarray(corners(make(size / 2, pos, quat, 1.0, num_slots)))[:n].reshape(-1, 3)
  lo, hi = c.min(0), c.max(0)
  scale = 1.0 / (hi - lo).max()
  return size / 2 * scale, (pos - (lo + hi) / 2) * scale, quat


MATERIAL_SETS = ("paper", "real")  # the paper's five of Table 1, or the real towers' four


def sample_configuration(rng: np.random.Generator, num_blocks: int,
                         material_set: str = "paper"):
  """Material ids (n,) (into `materials.ALL_MATERIAL_NAMES`) and densities (n,) kg/m^3 for
  one configuration; each block's material is uniform over the set."""
  if material_set not in MATERIAL_SETS:
    raise ValueError(f"material_set must be one of {MATERIAL_SETS}, got {material_set!r}")
  names = materials.MATERIAL_NAMES if material_set == "paper" else materials.REAL_MATERIAL_NAMES
  ids = rng.integers(0, len(names), num_blocks) + materials.ALL_MATERIAL_NAMES.index(names[0])
  slots = [rng.choice(materials.material_slots(materials.ALL_MATERIAL_NAMES[i])) for i in ids]
  return ids.astype(np.int32), slot_to_density(slots)


def sample_tower(rng: np.random.Generator, num_blocks: int | None = None, *,
                 rotate: float = 0.0, num_slots: int = NUM_SLOTS, material_set: str = "paper"):
  """One tower with one configuration: (Primitives (float32), material names)."""
  half_size, pos, quat = sample_geometry(rng, num_blocks, rotate=rotate, num_slots=num_slots)
  ids, density = sample_configuration(rng, len(half_size), material_set)
  names = [materials.ALL_MATERIAL_NAMES[i] for i in ids]
  return make(half_size, pos, quat, density, num_slots), names


def sample_configurations(rng: np.random.Generator, num_configs: int = CONFIGS_PER_TOWER,
                          num_blocks: int | None = None, *, rotate: float = 0.0,
                          size_noise: float = 0.0, num_slots: int = NUM_SLOTS,
                          material_set: str = "paper"):
  """One tower geometry with `num_configs` material configurations.

  Returns:
    (Primitives with a leading (num_configs,) axis, material ids (num_configs, K) int32
    padded with -1).
  """
  half_size, pos, quat = sample_geometry(rng, num_blocks, rotate=rotate,
                                         size_noise=size_noise, num_slots=num_slots)
  n = len(half_size)
  prims, ids = [], np.full((num_configs, num_slots), -1, np.int32)
  for c in range(num_configs):
    ids[c, :n], density = sample_configuration(rng, n, material_set)
    prims.append(make(half_size, pos, quat, density, num_slots))
  return stack(prims), ids


def sample_towers(seed: int, count: int, **kwargs) -> Primitives:
  """`count` towers (one configuration each) on a leading axis, reproducible from `seed`.

  Args:
    seed: an int >= 0.
    count: an int >= 1.
    **kwargs: `sample_tower`'s (num_blocks 1..5 or None for 2..5, rotate, size_noise, ...).
  """
  for name, value, least in (("seed", seed, 0), ("count", count, 1)):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
      raise ValueError(f"sample_towers: {name} must be an int >= {least}, got {value!r}")
  rng = np.random.default_rng(seed)
  return stack([sample_tower(rng, **kwargs)[0] for _ in range(count)])
