"""Towers with densities and their simulated trajectories, made on the device.

The density estimator (`ppdjax.nn.estimator`) learns to read densities from geometry and
motion. That needs no image, so its training data need no rendering: each object is a
fresh tower (`stream.sample_towers_jax`, the dataset's geometry distribution), one of the
five materials per block and a density slot uniform within the material's slots (the
dataset's `towers.sample_configuration`), simulated under the pushes by MJX with the
dataset's settings. `simulate_pool` makes a pool of them in chunks of ~65k rollouts
(where MJX is fastest); on an H100, 400k objects take about a minute.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import NUM_DENSITY_SLOTS, NUM_SLOTS, STEPS, slot_to_density_jax
from ppdjax.dataset.materials import MATERIAL_NAMES, material_slots
from ppdjax.dataset.stream import sample_towers_jax, voxelize_axis_aligned
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, Settings, simulate


def material_slot_mask() -> np.ndarray:
  """(5, 100) bool: which density slots each material (MATERIAL_NAMES order) may take."""
  mask = np.zeros((len(MATERIAL_NAMES), NUM_DENSITY_SLOTS), bool)
  for i, name in enumerate(MATERIAL_NAMES):
    mask[i, material_slots(name)] = True
  return mask


def sample_slots_jax(key: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(material ids, density slots), each shaped like `valid`: a uniform material per block,
  then a slot uniform within its slots; -1 and 0 where not valid."""
  k_mat, k_slot = jax.random.split(key)
  mat = jax.random.randint(k_mat, valid.shape, 0, len(MATERIAL_NAMES))
  logits = jnp.where(jnp.asarray(material_slot_mask())[mat], 0.0, -jnp.inf)
  slots = jax.random.categorical(k_slot, logits).astype(jnp.int32)
  return jnp.where(valid, mat, -1).astype(jnp.int32), jnp.where(valid, slots, 0)


def physics_batch(key: jax.Array, batch: int, *, steps: int = STEPS,
                  pushes: Pushes | None = None, settings: Settings = DEFAULT_SETTINGS,
                  num_slots: int = NUM_SLOTS) -> dict:
  """`batch` fresh towers with densities, simulated: {"primitives" (B, K), "slots" (B, K),
  "materials" (B, K), "trajectories" (B, P, steps, 7)}. Jittable."""
  k_towers, k_slots = jax.random.split(key)
  prims = sample_towers_jax(k_towers, batch, num_slots)
  mats, slots = sample_slots_jax(k_slots, prims.valid)
  prims = prims.replace(density=jnp.where(prims.valid, slot_to_density_jax(slots), 0.0))
  traj = simulate(prims, default_pushes() if pushes is None else pushes, steps=steps,
                  settings=settings)
  return {"primitives": prims, "slots": slots, "materials": mats, "trajectories": traj}


def training_batch(key: jax.Array, batch: int, *, steps: int, pushes: Pushes,
                   settings: Settings) -> dict:
  """A batch for the network (`training.streams`): fresh towers' voxels (the dataset's rule
  for axis-aligned boxes), their trajectories and their boxes with densities; no image (the
  network reads f_I = 0). Jittable."""
  b = physics_batch(key, batch, steps=steps, pushes=pushes, settings=settings)
  return {"voxels": voxelize_axis_aligned(b["primitives"]).astype(jnp.uint8),
          "trajectories": b["trajectories"], "primitives": b["primitives"]}


@functools.partial(jax.jit, static_argnames=("batch", "steps", "settings"))
def _physics_batch_jit(key, pushes, *, batch, steps, settings):
  return physics_batch(key, batch, steps=steps, pushes=pushes, settings=settings)


def default_chunk() -> int:
  """Objects simulated per call: 16,384 (65,536 rollouts) on an accelerator, 256 on a CPU."""
  return 256 if jax.default_backend() == "cpu" else 16384


def simulate_pool(seed: int, count: int, *, steps: int = STEPS, chunk: int | None = None,
                  pushes: Pushes | None = None, settings: Settings = DEFAULT_SETTINGS,
                  progress: bool = True, desc: str = "simulating") -> dict:
  """`count` objects of `physics_batch`, deterministic in `seed`, on the default device.

  Chunk c is `physics_batch(fold_in(key(seed), c))`, so a pool is a function of (seed,
  count, chunk). Trajectories are kept in float32 on the device ((count, P, steps, 7):
  29 kB per object at 256 steps).
  """
  if count < 1:
    raise ValueError(f"count must be >= 1, got {count}")
  chunk = min(default_chunk() if chunk is None else chunk, count)
  pushes = default_pushes() if pushes is None else pushes
  make = lambda k: _physics_batch_jit(k, pushes, batch=chunk, steps=steps, settings=settings)
  parts = []
  n_chunks = -(-count // chunk)
  with tqdm(total=count, desc=desc, unit="object", disable=not progress) as bar:
    for c in range(n_chunks):
      parts.append(make(jax.random.fold_in(jax.random.key(seed), c)))
      bar.update(min(chunk, count - c * chunk))
  pool = jax.tree.map(lambda *x: jnp.concatenate(x)[:count], *parts)
  bad = ~jnp.all(jnp.isfinite(pool["trajectories"]), axis=(1, 2, 3))
  if bool(bad.any()):
    raise FloatingPointError(f"{int(bad.sum())} of {count} simulated objects have non-finite "
                             "trajectories")
  return pool
