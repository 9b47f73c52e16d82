"""Materials and density slots (paper Table 1): slot k in 0..99 is density (k + 1) * 100 kg/m^3."""

from __future__ import annotations

import numpy as np

NUM_DENSITY_SLOTS = 100
SLOT_DENSITY = 100.0  # kg/m^3 per slot

# Inclusive slot ranges in units of 100 kg/m^3 (1-based, as in the paper's table).
MATERIALS: dict[str, tuple[tuple[int, int], ...]] = {
    "wood": ((1, 10),),
    "brick": ((11, 20),),
    "stone": ((21, 30),),
    "ceramic": ((31, 60),),
    "metal": ((21, 35), (71, 100)),
}
MATERIAL_NAMES = tuple(MATERIALS)


def material_slots(name: str) -> np.ndarray:
  """0-based density slots a material may take."""
  if name not in MATERIALS:
    raise ValueError(f"unknown material {name!r}; expected one of {MATERIAL_NAMES}")
  return np.concatenate([np.arange(lo - 1, hi) for lo, hi in MATERIALS[name]])


def slot_to_density(slot):
  """Density in kg/m^3 of a 0-based slot (array-friendly)."""
  return (np.asarray(slot) + 1) * SLOT_DENSITY


def density_to_slot(density):
  """Nearest 0-based slot of a density in kg/m^3, clipped to the slot range."""
  return np.clip(np.rint(np.asarray(density) / SLOT_DENSITY) - 1, 0,
                 NUM_DENSITY_SLOTS - 1).astype(np.int32)
