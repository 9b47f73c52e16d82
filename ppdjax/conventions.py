"""The project's fixed conventions, each defined once: time, slots, densities, observation keys.

World: z up, gravity -9.81 m/s^2, ground plane z = 0, SI units. Objects fit the unit cube
[-0.5, 0.5]^3 of their object frame (centred on the bounding box at rest). Quaternions
are (w, x, y, z). A trajectory is the object-frame pose after each step,
(px, py, pz, qw, qx, qy, qz).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

TIMESTEP = 1.0 / 300.0  # s, one simulation step
STEPS = 256  # recorded steps per push
REST_DEPTH = 1e-6  # m: at rest, the object's lowest point is this far below the ground
NUM_SLOTS = 5  # K: primitives per object, padded with invalid slots
VOXEL_RESOLUTION = 32  # occupancy grids are 32^3 over the unit cube
# Boxes are listed bottom to top (`primitives.bottom_to_top`); boxes whose centres lie
# within one voxel in height (chained) share a level and go from -x to +x, so that the
# parts of a tool lying flat have an order the voxels show (the centres of a tower's
# blocks are 2.7+ voxels apart in height, over 36,000 sampled towers: by height alone).
ORDER_LEVEL = 1.0 / VOXEL_RESOLUTION  # m

# Density classes (paper Table 1): slot k in 0..99 is density (k + 1) * 100 kg/m^3.
NUM_DENSITY_SLOTS = 100
SLOT_DENSITY = 100.0  # kg/m^3 per slot
MIN_DENSITY = SLOT_DENSITY  # slot 0
MAX_DENSITY = NUM_DENSITY_SLOTS * SLOT_DENSITY  # slot 99

# What a model observes of an object, in this order.
OBS_KEYS = ("voxels", "image", "trajectories")
# An optional observation: the newtons each of the P pushes had for this object, where they
# differ from object to object (the realistic tools' pushes scale with the tool's size);
# absent, the pushes' own magnitudes. Simulations of candidates use it; the network does not.
PUSH_MAGNITUDES = "push_magnitudes"
# The RGB-D row's physics observation (paper Table 2), read in place of the trajectories by
# a model with model.physics_input = "depth_video": (P, F, S, S) float32 depth in metres
# (z along the optical axis) of F frames per push, seen by the datasets' camera at S x S
# pixels (`dataset.depth_video`).
DEPTH_VIDEO = "depth_video"


def slot_to_density(slot) -> np.ndarray:
  """Density (kg/m^3, float) of 0-based slots; NumPy (see `slot_to_density_jax`)."""
  return (np.asarray(slot) + 1.0) * SLOT_DENSITY


def density_to_slot(density) -> np.ndarray:
  """Nearest 0-based slot (int32, clipped to 0..99) of densities in kg/m^3; NumPy."""
  slot = np.rint(np.asarray(density) / SLOT_DENSITY) - 1
  return np.clip(slot, 0, NUM_DENSITY_SLOTS - 1).astype(np.int32)


def slot_to_density_jax(slot: jax.Array) -> jax.Array:
  """`slot_to_density` in JAX (traceable, differentiable in nothing: slots are integers)."""
  return (slot + 1.0) * SLOT_DENSITY


def density_to_slot_jax(density: jax.Array) -> jax.Array:
  """`density_to_slot` in JAX (traceable)."""
  slot = jnp.rint(density / SLOT_DENSITY) - 1
  return jnp.clip(slot, 0, NUM_DENSITY_SLOTS - 1).astype(jnp.int32)
