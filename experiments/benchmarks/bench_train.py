"""Training throughput (samples/s) of a preset: model step alone vs loader + step vs loader alone.

  python experiments/benchmarks/bench_train.py --config=ppdjax/configs/paper.py --data=DIR \
      --batch_sizes=32,64,128 --steps=40

The peer of the full pipeline is the model step on a batch already on the device (the
ceiling); the ratio says how much the disk-to-device loader costs. Prints a markdown table
and writes it as JSON (--out).

With --variants, the model step of each variant of the preset (config overrides, e.g.
`image_bf16:model.image_dtype=bfloat16;no_image:model.use_image=False`) beside the
preset's, in one process on the same batch, at the first of --batch_sizes:

  python experiments/benchmarks/bench_train.py --data=DIR --batch_sizes=256 \
      --variants="image_bf16:model.image_dtype=bfloat16" --out=bench_train_variants.json
"""

from __future__ import annotations

import json
import sys
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
flags.DEFINE_string("variants", "", "'name:key=value,key=value;name:...': time these "
                    "variants' model step beside the preset's (ratios), nothing else.")
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
  from ppdjax.dataset import batching, storage
  from ppdjax.training.loader import BATCH_KEYS, Loader
  from ppdjax.training.state import Trainer

  ds = storage.open_dataset(FLAGS.data, "train")
  if FLAGS.variants:
    return compare_variants(ds, int(FLAGS.batch_sizes.split(",")[0]))
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
      it = batching.batches(ds, bs, seed=1, keys=BATCH_KEYS)
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


def _parse_value(text: str):
  for kind in (int, float):
    try:
      return kind(text)
    except ValueError:
      pass
  return {"True": True, "False": False}.get(text, text)


def compare_variants(ds, bs: int) -> None:
  """Model-step samples/s of the preset and of each --variants override set, in turn in
  this process on one fixed batch (a joint-phase step, the stream's loss beside it when
  the preset has one), with the ratio to the preset."""
  from ppdjax.training.loader import Loader
  from ppdjax.training.state import Trainer
  variants = [("preset", {})]
  for item in filter(None, FLAGS.variants.split(";")):
    name, _, sets = item.partition(":")
    variants.append((name, dict(kv.split("=", 1) for kv in sets.split(","))))
  rows = []
  for name, overrides in variants:
    config = FLAGS.config.copy_and_resolve_references()
    config.train.batch_size = bs
    for key, value in overrides.items():
      section, _, field = key.rpartition(".")
      config[section][field] = _parse_value(value)
    t = config.train
    joint_step = t.get("stream_steps", 0) + t.geometry_steps  # the first joint step
    with tempfile.TemporaryDirectory() as workdir:
      trainer = Trainer(config, workdir)
      loader = Loader(ds, bs, seed=0, start_step=0, prefetch=1, mesh=trainer.mesh)
      fixed = next(loader)
      loader.close()
      clock = time.perf_counter()
      jax.block_until_ready(trainer.train_step(fixed, joint_step, 0.5))
      first = time.perf_counter() - clock
      rate = _rate(lambda: trainer.train_step(fixed, joint_step, 0.5), FLAGS.steps, bs)
      trainer.close()
    rows.append({"variant": name, "overrides": overrides, "batch_size": bs,
                 "model_step_samples_s": round(rate, 1), "first_step_s": round(first, 1),
                 "vs_preset": round(rate / rows[0]["model_step_samples_s"], 3) if rows else 1.0})
    print(json.dumps(rows[-1]), flush=True)
  dev = jax.devices()[0]
  print(f"\n{FLAGS.config.name} preset, batch {bs}, on {jax.device_count()} x {dev.device_kind}\n")
  print("| variant | overrides | model step (samples/s) | × preset | first step (s) |")
  print("|---|---|--:|--:|--:|")
  for r in rows:
    sets = ", ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "–"
    print(f"| {r['variant']} | {sets} | {r['model_step_samples_s']} | {r['vs_preset']} | "
          f"{r['first_step_s']} |")
  if FLAGS.out:
    with open(FLAGS.out, "w") as f:
      json.dump({"command": ("python experiments/benchmarks/bench_train.py "
                             + " ".join(sys.argv[1:])),
                 "device": f"{jax.device_count()} x {dev.device_kind}", "rows": rows}, f, indent=1)


if __name__ == "__main__":
  app.run(main)
