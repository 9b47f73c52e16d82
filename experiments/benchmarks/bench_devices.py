"""Scaling over local devices: training steps/s and evaluation objects/s on the first device
alone (the peer) and on all local devices, side by side in one process.

  python experiments/benchmarks/bench_devices.py --data=DIR \
      --out=experiments/results/bench_devices/h100x2.json

Training (`Trainer(devices=...)`, the preset's model step on one fixed batch already on the
devices, after 3 warm-up steps): the same global batch split over N devices (strong
scaling: steps/s ratio) and N times the batch (weak scaling: each device's share as the
one device's; samples/s ratio), for each `--batch_norms` mode over all devices
(`train.batch_norm`: statistics over the whole batch, all-reduced at every normalisation,
or over each device's share, one average at the step's end). Evaluation (`evaluate(devices=...)`, the model's own
evaluation settings: fit, depth fit, baselines, refinement; the preset's network with random
weights unless --workdir names a trained one): `--eval_batch` objects a
device a batch, so each device runs the one device's programs; objects/s after the first
batch (which compiles) over the same `--objects` test objects. Efficiency = rate ratio / N
(1.0 is linear). Prints a markdown table and writes the rows as JSON (--out).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time

import jax
from absl import app, flags, logging
from ml_collections import config_flags

config_flags.DEFINE_config_file("config", "ppdjax/configs/paper.py", "Preset for training.")
flags.DEFINE_string("data", None, "Dataset directory (train and test splits).", required=True)
flags.DEFINE_string("workdir", "", "Trained model for the evaluation (empty: the preset's "
                    "network with random weights; the cost does not depend on them).")
flags.DEFINE_integer("train_batch", 256, "Training batch a device (the preset's: 256).")
flags.DEFINE_integer("steps", 30, "Timed training steps (after 3 warm-up steps).")
flags.DEFINE_integer("eval_batch", 64, "Evaluation objects a device a batch.")
flags.DEFINE_integer("objects", 768, "Test objects in each timed evaluation.")
flags.DEFINE_list("batch_norms", ["global"], "train.batch_norm modes timed over all devices "
                  "(global, per_device); one device runs one program for either.")
flags.DEFINE_bool("train", True, "Time training.")
flags.DEFINE_bool("evaluate", True, "Time the evaluation.")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
FLAGS = flags.FLAGS


def _steps_per_s(trainer, batch, steps: int) -> float:
  for i in range(3):
    out = trainer.train_step(batch, i, 0.5)
  jax.block_until_ready(out)
  t = time.perf_counter()
  for i in range(steps):
    out = trainer.train_step(batch, 3 + i, 0.5)
  jax.block_until_ready(out)
  return steps / (time.perf_counter() - t)


def time_training(ds, device_sets) -> list[dict]:
  from ppdjax.training.loader import Loader
  from ppdjax.training.state import Trainer
  rows = []
  n_all = len(device_sets[-1])
  cases = [(device_sets[0], FLAGS.train_batch, "peer", "global")]
  for mode in FLAGS.batch_norms:
    cases += [(device_sets[-1], FLAGS.train_batch, "strong", mode),
              (device_sets[-1], FLAGS.train_batch * n_all, "weak", mode)]
  for devices, global_batch, kind, mode in cases:
    config = FLAGS.config.copy_and_resolve_references()
    config.train.batch_size = global_batch
    config.train.batch_norm = mode
    with tempfile.TemporaryDirectory() as workdir:
      t = time.perf_counter()
      trainer = Trainer(config, workdir, devices=devices)
      loader = Loader(ds, global_batch, seed=0, start_step=0, prefetch=1, mesh=trainer.mesh)
      batch = next(loader)
      loader.close()
      jax.block_until_ready(trainer.train_step(batch, 0, 0.5))
      compile_s = time.perf_counter() - t
      rate = _steps_per_s(trainer, batch, FLAGS.steps)
      trainer.close()
    rows.append({"case": kind, "batch_norm": mode, "devices": len(devices),
                 "global_batch": global_batch,
                 "steps_per_s": rate, "samples_per_s": rate * global_batch,
                 "first_step_s": compile_s})
    print(f"train {kind}, batch norm {mode}: {len(devices)} device(s), batch {global_batch}: "
          f"{rate:.2f} steps/s "
          f"= {rate * global_batch:.0f} samples/s (first step {compile_s:.0f} s)", flush=True)
  peer = rows[0]
  for r in rows[1:]:
    key = "steps_per_s" if r["case"] == "strong" else "samples_per_s"
    r["ratio"] = r[key] / peer[key]
    r["efficiency"] = r["ratio"] / r["devices"]
  return rows


def time_evaluation(device_sets) -> list[dict]:
  from ppdjax.eval import evaluation
  from ppdjax.training import checkpoints
  if FLAGS.workdir:
    trained = checkpoints.load(FLAGS.workdir)
  else:
    from ppdjax.training.state import build
    config = FLAGS.config.copy_and_resolve_references()
    trained = (build(config).model, config)
  settings = evaluation.eval_settings(trained[1])
  rows = []
  for devices in (device_sets[0], device_sets[-1]):
    kw = dict(batch_size=FLAGS.eval_batch * len(devices))
    r = evaluation.evaluate(trained, FLAGS.data, settings, split="test",
                            max_objects=FLAGS.objects, progress=False, devices=devices, **kw)
    stage = r["seconds_by_stage"]
    after = r["objects"] - kw["batch_size"]
    steady = after / (r["seconds"] - stage["first_batch_wall"])
    rows.append({"devices": len(devices), "batch_size": kw["batch_size"],
                 "objects": r["objects"], "seconds": r["seconds"],
                 "first_batch_wall_s": stage["first_batch_wall"],
                 "objects_per_s_after_first": steady,
                 "objects_per_s_whole_call": r["objects"] / r["seconds"],
                 "seconds_by_part": r["seconds_by_part"],
                 "after_first_by_stage": stage["after_first"],
                 "table2_top1": {k: v["top1"] for k, v in r["table2"].items()}})
    print(f"evaluate: {len(devices)} device(s), batch {kw['batch_size']}: {r['objects']} "
          f"objects in {r['seconds']:.0f} s (first batch done at {stage['first_batch_wall']:.0f}"
          f" s), {steady:.2f} objects/s after it; by stage {stage['after_first']}; "
          f"by part {r['seconds_by_part']}", flush=True)
  rows[1]["ratio"] = rows[1]["objects_per_s_after_first"] / rows[0]["objects_per_s_after_first"]
  rows[1]["efficiency"] = rows[1]["ratio"] / rows[1]["devices"]
  # the same objects, but a batch's keys come from its first object's index, so batches
  # of another size draw other samples: the gap is sampling noise, not the devices
  rows[1]["table2_top1_max_gap"] = max(abs(v - rows[0]["table2_top1"][k])
                                       for k, v in rows[1]["table2_top1"].items())
  print(f"Table 2 top-1, largest gap between the two evaluations: "
        f"{rows[1]['table2_top1_max_gap']:.2f} points", flush=True)
  return rows


def markdown(train_rows, eval_rows) -> str:
  lines = ["| work | devices | batch | rate | × 1 device | efficiency |",
           "|---|--:|--:|--:|--:|--:|"]
  for r in train_rows:
    rate = f"{r['steps_per_s']:.2f} steps/s = {r['samples_per_s']:.0f} samples/s"
    bn = "" if r["devices"] == 1 else f", batch norm {r['batch_norm']}"
    lines.append(f"| training ({r['case']}{bn}) | {r['devices']} | {r['global_batch']} | {rate} | "
                 f"{r.get('ratio', 1.0):.2f} | {r.get('efficiency', 1.0):.2f} |")
  for r in eval_rows:
    lines.append(f"| evaluation | {r['devices']} | {r['batch_size']} | "
                 f"{r['objects_per_s_after_first']:.2f} objects/s | {r.get('ratio', 1.0):.2f} | "
                 f"{r.get('efficiency', 1.0):.2f} |")
  return "\n".join(lines)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  if not jax.config.jax_compilation_cache_dir:
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/ppdjax-jax"))
  from ppdjax.dataset import storage
  local = jax.local_devices()
  if len(local) < 2:
    raise SystemExit(f"bench_devices needs at least 2 local devices, found {local}")
  device_sets = [local[:1], local]
  dev = local[0].device_kind
  print(f"{len(local)} x {dev}; peer: the first device alone", flush=True)
  train_rows = (time_training(storage.open_dataset(FLAGS.data, "train"), device_sets)
                if FLAGS.train else [])
  eval_rows = time_evaluation(device_sets) if FLAGS.evaluate else []
  table = markdown(train_rows, eval_rows)
  print("\n" + table)
  if FLAGS.out:
    os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
    with open(FLAGS.out, "w") as f:
      json.dump({"command": ("python experiments/benchmarks/bench_devices.py "
                             + " ".join(sys.argv[1:])),
                 "device": f"{len(local)} x {dev}", "train": train_rows,
                 "evaluate": eval_rows, "markdown": table}, f, indent=1)


if __name__ == "__main__":
  app.run(main)
