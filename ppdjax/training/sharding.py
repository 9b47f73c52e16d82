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


def make_mesh(devices=None) -> Mesh:
  """A 1-D mesh over `devices` (None: every device of every process)."""
  return Mesh(np.array(jax.devices() if devices is None else list(devices)), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, PartitionSpec())


def batch_sharded(mesh: Mesh) -> NamedSharding:
  """Leading (batch) axis split over the mesh."""
  return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def check_batch_size(batch_size: int, devices: int | None = None) -> int:
  """The per-process batch; raises ValueError unless the batch splits evenly over
  `devices` (None: every device)."""
  devices, processes = devices or jax.device_count(), jax.process_count()
  if batch_size % devices:
    raise ValueError(f"train.batch_size={batch_size} must be a multiple of the "
                     f"{devices} devices it is split over")
  return batch_size // processes


def _place(tree, sharding):
  """Arrays put on `sharding`; abstract leaves (`jax.ShapeDtypeStruct`) given it."""
  def one(x):
    if isinstance(x, jax.ShapeDtypeStruct):
      return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=x.weak_type)
    return jax.device_put(x, sharding)
  return jax.tree.map(one, tree)


class _OverDevices:
  """`jit_over_local_devices`' function on a device or a mesh; `lower` takes arrays or
  `jax.ShapeDtypeStruct`s, as `jax.jit`'s does (ahead-of-time compilation)."""

  def __init__(self, fn, replicated: tuple[int, ...], devices: list):
    self.fn, self.replicated, self.devices, self.jitted = fn, replicated, devices, None
    self.mesh = Mesh(np.array(devices), (DATA_AXIS,)) if len(devices) > 1 else None

  def _prepare(self, args) -> tuple:
    """(the jitted function, the arguments placed for it), built on the first call."""
    if self.mesh is None:
      self.jitted = self.jitted or jax.jit(self.fn)
      return self.jitted, _place(list(args), jax.sharding.SingleDeviceSharding(self.devices[0]))
    specs = tuple(PartitionSpec() if i in self.replicated else PartitionSpec(DATA_AXIS)
                  for i in range(len(args)))
    if any(np.shape(x)[0] % len(self.devices) for a, p in zip(args, specs)
           if p != PartitionSpec() for x in jax.tree.leaves(a)):
      raise ValueError(f"a batch split over {len(self.devices)} devices must be a multiple of "
                       f"{len(self.devices)} long")
    if self.jitted is None:  # check_vma off: `fn` uses no collectives, and its scans'
      # carries (MJX's solver) mix per-device and replicated values the check would have
      # us mark
      self.jitted = jax.jit(jax.shard_map(self.fn, mesh=self.mesh, in_specs=specs,
                                          out_specs=PartitionSpec(DATA_AXIS), check_vma=False))
    # arguments committed to one device (the model's weights) move onto the mesh first
    return self.jitted, [_place(a, NamedSharding(self.mesh, p)) for a, p in zip(args, specs)]

  def __call__(self, *args):
    jitted, placed = self._prepare(args)
    return jitted(*placed)

  def lower(self, *args):
    jitted, placed = self._prepare(args)
    return jitted.lower(*placed)


def jit_over_local_devices(fn, replicated: tuple[int, ...] = (), devices=None):
  """`jax.jit(fn)`, each local device running `fn` on its share of a batch (`jax.shard_map`):
  every argument is split along its leading axis except those at the positions in
  `replicated`, which each device gets whole; every output keeps the batch axis. On one
  device, plain `jax.jit(fn)` placed on it. `devices`: the local devices to use (None: all).
  Either way the result has `lower` (arrays or `jax.ShapeDtypeStruct`s), for compiling
  ahead of time.

  For per-object work (the evaluation): the batch must split evenly over the devices.
  """
  if devices is None and len(jax.local_devices()) == 1:
    return jax.jit(fn)
  return _OverDevices(fn, replicated, jax.local_devices() if devices is None else list(devices))


def global_batch(local_tree, sharding: NamedSharding):
  """One global array per leaf from this process's rows (the whole batch on one host)."""
  return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, x),
                      local_tree)
