"""The batches of fresh towers a training step draws beside the dataset's, each a function
of (train.seed, step) so that a resumed run sees exactly what an uninterrupted one would.

- The geometry stream (`train.stream_steps`, `train.stream_weight`): voxels of fresh towers
  (`dataset.stream`), for the voxel pathway and the geometry heads.
- The physics stream (`train.physics_stream_weight`): fresh towers with densities drawn as
  the dataset's, simulated under its pushes by its engine inside the step
  (`dataset.physics_stream`), with no image: unlimited motion for the trajectory pathway
  and the density head, which overfit the dataset's tens of thousands of samples
  (experiments/blocks_longer).
"""

from __future__ import annotations

import jax

from ppdjax.dataset import physics_stream, stream
from ppdjax.sim.rollout_mjx import settings_for

STREAM_SEED = 7_919  # offsets the stream's key from the dropout key of the same seed
VAL_STREAM_SEED = 7_920  # a held-out stream: validation of a run that reads no dataset
PHYSICS_SEED = 7_921  # the physics stream's


def _key(seed: int, step, axis):
  """The step's key; inside a per-device step each device folds in its index too."""
  key = jax.random.fold_in(jax.random.key(seed), step)
  return key if axis is None else jax.random.fold_in(key, jax.lax.axis_index(axis))


def _placed(batch, sharding):
  return batch if sharding is None else jax.lax.with_sharding_constraint(batch, sharding)


def geometry_batch(t, step, sharding=None, axis=None, devices=1) -> dict:
  """The geometry stream's batch for `step`: {"voxels", "primitives"} of the device's share
  (`axis`, the mesh axis of `devices` devices, inside a per-device step)."""
  batch = stream.geometry_batch(_key(t.seed + STREAM_SEED, step, axis),
                                t.batch_size // devices, t.get("augment", True))
  return _placed(batch, sharding)


def physics_batch_fn(data):
  """`(t, step, sharding, axis, devices) -> batch` of the physics stream for a data section
  (its pushes, steps and engine): {"voxels", "trajectories", "primitives"}, no image."""
  from ppdjax.dataset.generation import pushes_of  # pylint: disable=import-outside-toplevel
  pushes, settings = pushes_of(data), settings_for(data.backend)

  def make(t, step, sharding=None, axis=None, devices=1) -> dict:
    batch = physics_stream.training_batch(_key(t.seed + PHYSICS_SEED, step, axis),
                                          t.batch_size // devices, steps=data.steps,
                                          pushes=pushes, settings=settings)
    return _placed(batch, sharding)
  return make
