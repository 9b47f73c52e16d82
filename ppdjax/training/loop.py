"""The training loop: `train_and_evaluate(config, data_dir, workdir)`, resumable exactly.

An optional geometry stream first (voxels of fresh towers; `dataset.stream`), then two
phases as in the paper's appendix (geometry only with w = 0, then everything), Adam,
data parallel over all devices, orbax checkpoints with exact resume, metrics.jsonl,
TensorBoard events and a learning-curve PNG. Rerun the same command to resume.
"""

from __future__ import annotations

import json
import os
import time

import jax
import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import DEPTH_VIDEO
from ppdjax.dataset import storage
from ppdjax.dataset.depth_video import frame_steps
from ppdjax.nn.model import physics_key
from ppdjax.configs import schema
from ppdjax.report.plots import plot_learning_curve
from ppdjax.training import checkpoints, sharding
from ppdjax.training.loader import Loader
from ppdjax.training.state import Trainer, batch_norm_mode, density_weight, phase, total_steps


# Keys a resumed run may change without invalidating its checkpoints.
RESUMABLE_CHANGES = ("train.joint_steps", "train.log_every", "train.eval_every",
                     "train.eval_batches", "train.prefetch", "train.keep_checkpoints",
                     "model.trajectory_unroll",  # the same arithmetic, scheduled differently
                     "train.batch_norm")  # the same on one device; checkpoints unchanged


def check_config(config) -> None:
  """Raises ValueError naming the first bad value of the model and train sections."""
  t, m = config.train, config.model
  positive = {"train.batch_size": t.batch_size, "train.learning_rate": t.learning_rate,
              "train.log_every": t.log_every, "train.eval_every": t.eval_every,
              "train.keep_checkpoints": t.keep_checkpoints, "model.feature": m.feature,
              "model.hidden": m.hidden, "model.generator_layers": m.generator_layers,
              "model.resnet_width": m.resnet_width, "model.num_pushes": m.num_pushes}
  for name, value in positive.items():
    if not value > 0:
      raise ValueError(f"config.{name} must be > 0, got {value}")
  for name in ("stream_steps", "geometry_steps", "joint_steps", "eval_batches", "prefetch",
               "end_weight", "geometry_weight", "stream_weight", "clip_norm", "warmup_steps",
               "density_ramp_steps", "physics_stream_weight"):
    if t.get(name) is not None and t.get(name, 0) < 0:
      raise ValueError(f"config.train.{name} must be >= 0, got {t[name]}")
  if total_steps(t) == 0:
    raise ValueError("config.train.stream_steps + geometry_steps + joint_steps must be > 0")
  batch_norm_mode(t)
  if (t.get("stream_steps", 0) or t.get("stream_weight", 0)) and not m.use_voxels:
    raise ValueError("config.train.stream_steps / stream_weight train the voxel pathway; "
                     "this model has use_voxels=False: set them to 0")
  if t.get("physics_stream_weight", 0) > 0 and (config.data.get("kind", "towers") != "towers"
                                                or not m.use_trajectory):
    raise ValueError("config.train.physics_stream_weight simulates fresh towers of the paper's "
                     "materials under the paper's pushes: it needs data.kind 'towers' and a "
                     "model that reads the motion (use_trajectory)")
  if t.get("init_from", "") and not os.path.isdir(t.init_from):
    raise ValueError(f"config.train.init_from={t.init_from!r} is not a directory")
  if not 0 <= m.dropout < 1:
    raise ValueError(f"config.model.dropout must be in [0, 1), got {m.dropout}")
  if t.density_weight < 0:
    raise ValueError(f"config.train.density_weight must be >= 0, got {t.density_weight}")
  if m.max_primitives != 5:
    raise ValueError("config.model.max_primitives must be 5 (datasets pad to 5 boxes)")
  if not (m.use_voxels or m.use_image or m.use_trajectory):
    raise ValueError("config.model: at least one of use_voxels, use_image, use_trajectory")
  if physics_key(m) == DEPTH_VIDEO:  # (and names a bad physics_input)
    frame_steps(m.video_frames, config.data.steps)  # names a bad frame count
    if m.video_size < 16 or m.video_size % 16:
      raise ValueError(f"config.model.video_size must be a multiple of 16, got {m.video_size}")


def _flatten(d, prefix=""):
  out = {}
  for k, v in d.items():
    out.update(_flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
  return out


def _check_resume(workdir: str, config) -> None:
  """Refuses to resume a run made with another model, data or optimiser setting."""
  if not os.path.exists(os.path.join(workdir, "config.json")):
    return
  old = _flatten(json.loads(checkpoints.read_config(workdir).to_json_best_effort()))
  new = _flatten(json.loads(config.to_json_best_effort()))
  changed = sorted(k for k in set(old) | set(new)
                   if k not in RESUMABLE_CHANGES and not k.startswith("eval.")  # not training's
                   and json.dumps(old.get(k)) != json.dumps(new.get(k)))
  if changed:
    raise ValueError(f"{workdir} holds a run made with another config ({', '.join(changed)} "
                     "differ); use a new --workdir")


def train_and_evaluate(config, data_dir: str, workdir: str, progress: bool = True,
                       time_limit_s: float | None = None) -> dict:
  """Trains (or resumes) a PPD model; returns the last validation metrics.

  Args:
    config: a preset with `model` and `train` sections.
    data_dir: a generated dataset with train and val splits (not read by a run of the
      geometry stream alone, which validates on a held-out stream of fresh towers).
    workdir: checkpoints, config.json, metrics.jsonl, tensorboard/ and learning_curve.png.
    progress: show a progress bar.
    time_limit_s: if set, stop after about this many seconds of steps with a checkpoint
      (rerun to resume); `trained_steps(workdir)` then tells how far the run got.
  """
  config = schema.complete(config)  # unknown or ill-typed keys named; defaults filled
  check_config(config)
  t = config.train
  sharding.check_batch_size(t.batch_size)
  # a run of the geometry stream alone reads no dataset (it may start before one exists)
  stream_only = total_steps(t) == t.get("stream_steps", 0)
  train_ds = val_ds = None
  if not stream_only:
    train_ds = storage.open_dataset(data_dir, "train")
    val_ds = storage.open_dataset(data_dir, "val")
    pushes = train_ds[0]["trajectories"].shape[0]
    if pushes != config.model.num_pushes:
      raise ValueError(f"{data_dir} has {pushes} pushes per sample; config.model.num_pushes "
                       f"is {config.model.num_pushes}")
    if len(train_ds) < t.batch_size:
      raise ValueError(f"the train split has {len(train_ds)} samples, fewer than "
                       f"train.batch_size={t.batch_size}")
  _check_resume(workdir, config)
  checkpoints.save_config(workdir, config, train_ds.camera if train_ds is not None else None)
  if trained_steps(workdir) >= total_steps(t):  # finished: no model to build, no step left
    return _last_validation(os.path.join(workdir, "metrics.jsonl"))

  trainer = Trainer(config, workdir)
  start = trainer.restore_latest()
  total = total_steps(t)
  log = MetricsLog(workdir, start, enabled=jax.process_index() == 0)
  stream_steps = t.get("stream_steps", 0)  # the loader's step counts dataset steps only
  loader = (None if stream_only else
            Loader(train_ds, t.batch_size, seed=t.seed, start_step=max(start - stream_steps, 0),
                   prefetch=t.prefetch, mesh=trainer.mesh))
  bar = tqdm(total=total, initial=start, desc="train", unit="step", disable=not progress,
             dynamic_ncols=True)
  pending, tick, step, last_val = [], time.perf_counter(), start, None
  deadline = None if time_limit_s is None else time.perf_counter() + time_limit_s
  try:
    for step in range(start, total):
      if deadline is not None and time.perf_counter() > deadline and step > start:
        print(f"\ntime limit: stopping at step {step}; run again to resume", flush=True)
        if step not in trainer.latest.all_steps():
          trainer.save(step, None)
        break
      now_phase = phase(t, step)
      w = density_weight(t, step)
      pending.append(trainer.train_step(next(loader) if now_phase else None, step, w))
      done = step + 1
      if (done % t.log_every == 0 or done == total
          or phase(t, min(done, total - 1)) != now_phase):  # a row never spans two phases
        row = {k: float(np.mean([m[k] for m in jax.device_get(pending)])) for k in pending[0]}
        now = time.perf_counter()
        row.update(step=done, phase=now_phase,
                   samples_per_s=round(len(pending) * t.batch_size / (now - tick), 2))
        log.write(row)
        bar.set_postfix(loss=f"{row['loss']:.3f}", phase=row["phase"])
        pending, tick = [], now
      if done % t.eval_every == 0 or done == total:
        last_val = trainer.evaluate(val_ds, t.eval_batches)
        log.write({"step": done, "split": "val", **last_val})
        trainer.save(done, last_val["loss"])
        tick = time.perf_counter()
      bar.update(1)
  except KeyboardInterrupt:
    done = step  # the step in flight did not finish
    if done > start:
      print(f"\ninterrupted: saving step {done}; run the same command to resume", flush=True)
      trainer.save(done, None)
    raise
  finally:
    bar.close()
    if loader is not None:
      loader.close()
    trainer.close()
    log.close()
  if last_val is None:  # stopped before a validation: report the run's last one
    last_val = _last_validation(log.path)
  if jax.process_index() == 0:
    plot_learning_curve(log.path, os.path.join(workdir, "learning_curve.png"))
  return last_val


def _last_validation(metrics_path: str) -> dict:
  """The last validation row of a run's metrics.jsonl, without its step and split."""
  rows = []
  if os.path.exists(metrics_path):
    with open(metrics_path) as f:
      rows = [json.loads(line) for line in f if '"val"' in line]
  return {k: v for k, v in rows[-1].items() if k not in ("step", "split")} if rows else {}


def trained_steps(workdir: str) -> int:
  """The step of a workdir's latest checkpoint (0 if it has none)."""
  path = os.path.join(workdir, checkpoints.LATEST)
  steps = [int(d) for d in os.listdir(path) if d.isdigit()] if os.path.isdir(path) else []
  return max(steps, default=0)


class MetricsLog:
  """WORKDIR/metrics.jsonl (one JSON object per row) and TensorBoard events.

  On resume, rows after the restored step are dropped, so the file reads as if the run
  had never stopped.
  """

  def __init__(self, workdir: str, start_step: int, enabled: bool = True):
    from tensorboardX import SummaryWriter
    self.path, self.enabled = os.path.join(workdir, "metrics.jsonl"), enabled
    if not enabled:
      return
    rows = []
    if os.path.exists(self.path):
      with open(self.path) as f:
        rows = [line for line in f if line.strip() and json.loads(line)["step"] <= start_step]
    with open(self.path, "w") as f:
      f.writelines(rows)
    self.writer = SummaryWriter(os.path.join(workdir, "tensorboard"), purge_step=start_step + 1)

  def write(self, row: dict) -> None:
    if not self.enabled:
      return
    with open(self.path, "a") as f:
      f.write(json.dumps(row) + "\n")
    prefix = row.get("split", "train")
    for k, v in row.items():
      if k not in ("step", "split") and isinstance(v, (int, float)):
        self.writer.add_scalar(f"{prefix}/{k}", v, row["step"])

  def close(self) -> None:
    if self.enabled:
      self.writer.close()
