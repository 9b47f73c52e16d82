"""Hollow and filled blocks: a shell of the block's material around a core of another.

A look-alike of the paper's Fig. 5: the block shows its shell's material, while its mass
and inertia are the shell's and the core's together. The core is a centred box of the
block's proportions, `f` of its size along each axis (volume fraction f^3): empty (air)
or of another of the real materials. The label is the block's mean density; the
simulator reads the rest of its mass distribution as `Primitives.inertia_scale`, the
block's inertia about its centre over that of a uniform block of its mean density: a box's
inertia scales with density x size^5, so for a shell of density s around a core of c,

  mean  = s (1 - f^3) + c f^3
  scale = (s (1 - f^5) + c f^5) / mean.
"""

from __future__ import annotations

import numpy as np

from ppdjax.conventions import MAX_DENSITY, MIN_DENSITY, slot_to_density
from ppdjax.dataset import materials
from ppdjax.primitives import Primitives

# The core's linear fraction of the block (its volume 22-61 % of the block's).
CORE_FRACTION = (0.6, 0.85)
EMPTY_CORE = 0.5  # the chance that a hollow block's core is empty (else another material)


def mean_density(shell, core, fraction):
  """The block's mean density (kg/m^3) of a shell around a core `fraction` of its size."""
  f3 = np.asarray(fraction) ** 3
  return np.asarray(shell) * (1 - f3) + np.asarray(core) * f3


def inertia_scale(shell, core, fraction):
  """The block's inertia over a uniform block's of its mean density (1 without a core)."""
  f5 = np.asarray(fraction) ** 5
  return (np.asarray(shell) * (1 - f5) + np.asarray(core) * f5) / mean_density(
      shell, core, fraction)


def hollow_blocks(rng: np.random.Generator, prims: Primitives, material_ids,
                  probability: float) -> tuple[Primitives, dict]:
  """Makes each valid block hollow with `probability`: its density the mean, its
  `inertia_scale` set (1 for solid blocks); the labels' materials stay the shell's.

  Args:
    rng: the generator (the core's size, whether it is empty, its material).
    prims: (..., K) blocks of the real materials at their densities.
    material_ids: (..., K) `materials.ALL_MATERIAL_NAMES` ids (-1 padding).
    probability: the chance that a block is hollow, in [0, 1].

  Returns:
    (Primitives with mean densities and inertia_scale, {"core_fraction": (..., K), 0 for
    a solid block; "core_density": (..., K) kg/m^3, 0 for an empty core}).
  """
  if not 0.0 <= probability <= 1.0:
    raise ValueError(f"data.hollow must be a probability in [0, 1], got {probability!r}")
  ids, valid = np.asarray(material_ids), np.asarray(prims.valid)
  shell = np.where(valid, np.asarray(prims.density, np.float64), 1.0)  # padding: any
  hollow = valid & (rng.random(ids.shape) < probability)
  fraction = np.where(hollow, rng.uniform(*CORE_FRACTION, ids.shape), 0.0)
  real = slot_to_density([materials.material_slots(n)[0]  # kg/m^3
                          for n in materials.REAL_MATERIAL_NAMES])
  other = rng.integers(0, len(real), ids.shape)
  core = np.where(rng.random(ids.shape) < EMPTY_CORE, 0.0, real[other])
  core = np.where(hollow, core, 0.0)
  mean = np.where(hollow, mean_density(shell, core, fraction), shell)
  scale = np.where(hollow, inertia_scale(shell, core, fraction), 1.0)
  # within the slots' range: the lightest, an empty pine shell, is 500 (1 - 0.85^3) = 193
  assert np.all(~valid | ((mean >= MIN_DENSITY) & (mean <= MAX_DENSITY)))
  out = prims.replace(density=np.where(valid, mean, 0.0).astype(np.float32),
                      inertia_scale=scale.astype(np.float32))
  return out.validate(), {"core_fraction": fraction.astype(np.float32),
                          "core_density": core.astype(np.float32)}
