"""Data parallelism with `jax.sharding`: one mesh axis over all devices, batch split, params replicated."""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"


def maybe_initialize_distributed() -> None:
  """Calls `jax.distributed.initialize()` for multi-host runs.

  A run is multi-host when JAX_COORDINATOR_ADDRESS (with JAX_NUM_PROCESSES and
  JAX_PROCESS_ID) is set, or when a cluster JAX detects itself (SLURM, Cloud TPU) sets
  PPDJAX_DISTRIBUTED=1. Single-host runs skip it.
  """
  if os.environ.get("JAX_COORDINATOR_ADDRESS") or os.environ.get("PPDJAX_DISTRIBUTED") == "1":
    jax.distributed.initialize()


def make_mesh() -> Mesh:
  """A 1-D mesh over every device of every process."""
  return Mesh(np.array(jax.devices()), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, PartitionSpec())


def batch_sharded(mesh: Mesh) -> NamedSharding:
  """Leading (batch) axis split over the mesh."""
  return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def check_batch_size(batch_size: int) -> int:
  """The per-process batch; raises ValueError unless the batch splits evenly."""
  devices, processes = jax.device_count(), jax.process_count()
  if batch_size % devices:
    raise ValueError(f"train.batch_size={batch_size} must be a multiple of the "
                     f"{devices} devices it is split over")
  return batch_size // processes


def global_batch(local_tree, sharding: NamedSharding):
  """One global array per leaf from this process's rows (the whole batch on one host)."""
  return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, x),
                      local_tree)
