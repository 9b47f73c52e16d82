"""Training throughput (samples/s) of a preset: model step alone vs loader + step vs loader alone.

  python experiments/bench_train.py --config=ppdjax/configs/paper.py --data=DIR \
      --batch_sizes=32,64,128 --steps=40

The peer of the full pipeline is the model step on a batch already on the device (the
ceiling); the ratio says how much the disk-to-device loader costs. Prints a markdown table
and writes it as JSON (--out).
"""

from __future__ import annotations

import json
import tempfile
import time

import jax
from absl import app, flags, logging
from ml_collections import config_flags

config_flags.DEFINE_config_file("config", "ppdjax/configs/paper.py", "Preset file.")
flags.DEFINE_string("data", None, "Dataset directory.", required=True)
flags.DEFINE_string("batch_sizes", "32,64,128", "Global batch sizes to time.")
flags.DEFINE_integer("steps", 40, "Timed steps per measurement (after 3 warm-up steps).")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
FLAGS = flags.FLAGS


def _rate(fn, steps, batch_size):
  for _ in range(3):
    out = fn()
  jax.block_until_ready(out)
  t = time.perf_counter()
  for _ in range(steps):
    out = fn()
  jax.block_until_ready(out)
  return steps * batch_size / (time.perf_counter() - t)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  from ppdjax.dataset import storage
  from ppdjax.training.loader import BATCH_KEYS, Loader
  from ppdjax.training.state import Trainer

  ds = storage.open_dataset(FLAGS.data, "train")
  rows = []
  for bs in [int(b) for b in FLAGS.batch_sizes.split(",")]:
    config = FLAGS.config.copy_and_resolve_references()
    config.train.batch_size = bs
    with tempfile.TemporaryDirectory() as workdir:
      trainer = Trainer(config, workdir)
      t = time.perf_counter()
      loader = Loader(ds, bs, seed=0, start_step=0, prefetch=config.train.prefetch,
                      mesh=trainer.mesh)
      fixed = next(loader)
      jax.block_until_ready(trainer.train_step(fixed, 0, 0.5))
      compile_s = time.perf_counter() - t
      step = [0]

      def model_only():
        step[0] += 1
        return trainer.train_step(fixed, step[0], 0.5)

      def pipeline():
        step[0] += 1
        return trainer.train_step(next(loader), step[0], 0.5)

      model = _rate(model_only, FLAGS.steps, bs)
      full = _rate(pipeline, FLAGS.steps, bs)
      loader.close()
      it = storage.batches(ds, bs, seed=1, keys=BATCH_KEYS)
      read = _rate(lambda: next(it)["image"], min(FLAGS.steps, len(ds) // bs - 4), bs)
      trainer.close()
    row = {"batch_size": bs, "model_step_samples_s": round(model, 1),
           "pipeline_samples_s": round(full, 1), "loader_alone_samples_s": round(read, 1),
           "pipeline_vs_model": round(full / model, 3), "first_step_s": round(compile_s, 1)}
    rows.append(row)
    print(json.dumps(row), flush=True)
  dev = jax.devices()[0]
  print(f"\n{config.name} preset on {jax.device_count()} x {dev.device_kind}; "
        f"resnet_width {config.model.resnet_width}; images {ds[0]['image'].shape}\n")
  print("| batch | model step (samples/s) | loader + step | loader alone | pipeline / model | first step (s) |")
  print("|---|---|---|---|---|---|")
  for r in rows:
    print(f"| {r['batch_size']} | {r['model_step_samples_s']} | {r['pipeline_samples_s']} | "
          f"{r['loader_alone_samples_s']} | {r['pipeline_vs_model']} | {r['first_step_s']} |")
  if FLAGS.out:
    with open(FLAGS.out, "w") as f:
      json.dump({"device": dev.device_kind, "devices": jax.device_count(), "rows": rows}, f,
                indent=1)


if __name__ == "__main__":
  app.run(main)
