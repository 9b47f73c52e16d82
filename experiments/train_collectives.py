"""The collectives in a compiled training step over N devices: how many, of what size.

  XLA_FLAGS=--xla_force_host_platform_device_count=2 JAX_PLATFORMS=cpu \
    python experiments/train_collectives.py --data=DIR --devices=2

What a step over several devices adds to one device's step is its collectives (the
gradient all-reduce, the synchronised BatchNorm statistics, any resharding the
partitioner inserts). This compiles the preset's training step for one device and for
`--devices` devices (weak scaling: `--batch` a device) and counts the collective
operations in each optimised HLO module, by kind, with their bytes. It needs no
accelerator: forced CPU devices compile the same partitioned program (the GPU backend may
fuse or combine collectives differently; `--xla_gpu_all_reduce_combine_threshold_bytes`
is its knob). DIR is any dataset (its dtypes are read; the preset's image size is used).
`--config.train.batch_norm=global` or `per_device` picks where BatchNorm's statistics
come from (the paper preset on two devices: 58 all-reduces of 211 MB a step against one
of 70 MB).
"""

from __future__ import annotations

import collections
import re
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from ml_collections import config_flags

config_flags.DEFINE_config_file("config", "ppdjax/configs/paper.py", "Preset.")
flags.DEFINE_string("data", None, "A dataset (only its arrays' dtypes are read).",
                    required=True)
flags.DEFINE_integer("devices", 2, "Devices of the partitioned step (at least 2).")
flags.DEFINE_integer("batch", 256, "Training batch a device.")
FLAGS = flags.FLAGS

COLLECTIVE = re.compile(r"=\s*(\([^()]*\)|\S+)\s+(all-reduce|all-gather|reduce-scatter|"
                        r"collective-permute|all-to-all)(?:-start)?\(")
BYTES = {"f32": 4, "s32": 4, "u32": 4, "bf16": 2, "f16": 2, "pred": 1, "u8": 1, "s8": 1,
         "f64": 8, "s64": 8}


def _bytes(shape: str) -> int:
  """Bytes of an HLO result shape such as f32[256,64] or (f32[3], f32[4,4])."""
  total = 0
  for dtype, dims in re.findall(r"(\w+)\[([\d,]*)\]", shape):
    total += BYTES.get(dtype, 4) * int(np.prod([int(d) for d in dims.split(",") if d] or [1]))
  return total


def collectives(hlo: str) -> dict:
  """kind -> (count, bytes) of the collectives in an optimised HLO module's text."""
  out = collections.defaultdict(lambda: [0, 0])
  for shape, kind in COLLECTIVE.findall(hlo):
    out[kind][0] += 1
    out[kind][1] += _bytes(shape)
  return dict(out)


def compiled_step(config, devices, sample) -> str:
  from ppdjax.training import sharding
  from ppdjax.training.state import Trainer
  batch_size = FLAGS.batch * len(devices)
  config.train.batch_size = batch_size
  image = (config.data.image_size, config.data.image_size, 3)
  with tempfile.TemporaryDirectory() as workdir:
    trainer = Trainer(config, workdir, devices=devices)
    spec = sharding.batch_sharded(trainer.mesh)

    def abstract(path, x):
      shape = image if jax.tree_util.keystr(path) == "['image']" else x.shape[1:]
      return jax.ShapeDtypeStruct((batch_size,) + tuple(shape), x.dtype, sharding=spec)

    batch = jax.tree_util.tree_map_with_path(abstract, sample)
    lowered = trainer._train.lower(trainer.state, batch, jnp.int32(0), jnp.float32(0.5))
    text = lowered.compile().as_text()
    trainer.close()
  return text


def main(argv):
  del argv
  from ppdjax.dataset import storage
  from ppdjax.training.loader import BATCH_KEYS
  if FLAGS.devices < 2 or jax.device_count() < FLAGS.devices:
    sys.exit(f"--devices={FLAGS.devices} needs at least 2 devices and no more than the "
             f"{jax.device_count()} there are (on a CPU: XLA_FLAGS="
             f"--xla_force_host_platform_device_count=N)")
  sample = storage.open_dataset(FLAGS.data, "train").take(np.arange(2), keys=BATCH_KEYS)
  config = FLAGS.config.copy_and_resolve_references()
  rows = {}
  for n in (1, FLAGS.devices):
    rows[n] = collectives(compiled_step(config.copy_and_resolve_references(),
                                        jax.devices()[:n], sample))
  print(f"| collective | 1 device | {FLAGS.devices} devices (count, MB) |")
  print("|---|--:|--:|")
  for kind in sorted(set(rows[1]) | set(rows[FLAGS.devices])):
    one, many = rows[1].get(kind, [0, 0]), rows[FLAGS.devices].get(kind, [0, 0])
    print(f"| {kind} | {one[0]} ({one[1] / 1e6:.2f}) | {many[0]} ({many[1] / 1e6:.2f}) |")


if __name__ == "__main__":
  app.run(main)
