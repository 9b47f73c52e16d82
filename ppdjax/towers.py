"""Random block towers (paper Sec. 5.1), scaled so the largest extent is 1 m and centred."""

from __future__ import annotations

import numpy as np

from ppdjax import materials
from ppdjax.primitives import NUM_SLOTS, Primitives, make

# Block full extents before scaling (arbitrary units; only ratios matter after scaling):
# footprints 0.5-1.5 wide and 0.3-1.0 tall give towers from squat to slender.
WIDTH_RANGE = (0.5, 1.5)
HEIGHT_RANGE = (0.3, 1.0)


def sample_tower(rng: np.random.Generator, num_blocks: int | None = None, *,
                 rotate: float = 0.0, num_slots: int = NUM_SLOTS):
  """One tower: block k+1 is centred at N(x_k, w_k/4), N(y_k, d_k/4) and rests on block k.

  Args:
    rng: numpy Generator.
    num_blocks: 2..num_slots, or None for uniform in that range.
    rotate: if > 0, each block gets a random rotation of up to this angle (radians) about
      a random axis (the paper's noise for tool pretraining); towers stay stacked by their
      unrotated extents, so rotated towers may overlap slightly.
    num_slots: K, the padded count.

  Returns:
    (Primitives (one object, float32), material names (num_blocks,)).
  """
  n = int(rng.integers(2, num_slots + 1)) if num_blocks is None else int(num_blocks)
  if not 1 <= n <= num_slots:
    raise ValueError(f"num_blocks must be in 1..{num_slots}, got {n}")
  size = np.column_stack([rng.uniform(*WIDTH_RANGE, n), rng.uniform(*WIDTH_RANGE, n),
                          rng.uniform(*HEIGHT_RANGE, n)])
  pos = np.zeros((n, 3))
  pos[0, 2] = size[0, 2] / 2
  for k in range(1, n):
    pos[k, 0] = rng.normal(pos[k - 1, 0], size[k - 1, 0] / 4)
    pos[k, 1] = rng.normal(pos[k - 1, 1], size[k - 1, 1] / 4)
    pos[k, 2] = pos[k - 1, 2] + (size[k - 1, 2] + size[k, 2]) / 2
  lo, hi = (pos - size / 2).min(0), (pos + size / 2).max(0)
  scale = 1.0 / (hi - lo).max()
  half_size = size / 2 * scale
  pos = (pos - (lo + hi) / 2) * scale
  quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
  if rotate > 0:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, rotate, n)
    quat = np.column_stack([np.cos(angle / 2), axis * np.sin(angle / 2)[:, None]])
  names = [materials.MATERIAL_NAMES[i] for i in rng.integers(0, len(materials.MATERIALS), n)]
  slots = [rng.choice(materials.material_slots(name)) for name in names]
  density = materials.slot_to_density(slots)
  return make(half_size, pos, quat, density, num_slots), names


def sample_towers(seed: int, count: int, **kwargs) -> Primitives:
  """`count` towers stacked on a leading axis (numpy arrays), reproducible from `seed`."""
  rng = np.random.default_rng(seed)
  towers = [sample_tower(rng, **kwargs)[0] for _ in range(count)]
  return Primitives(*[np.stack([getattr(t, f) for t in towers]) for f in
                      ("half_size", "pos", "quat", "density", "valid")])
