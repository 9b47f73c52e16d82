"""Evaluation on a dataset split: paper Tables 2, 4 and 5 for one trained model.

Per batch, one jitted call decodes the objects and simulates, with the data's engine, the
network's S density samples (candidate 0 its arg-max), Table 4's sampling baselines (S
uniform densities on the true shape; S random tower shapes with uniform densities) and
Table 2's guesses on the true shape; with refinement, a second fits the closest sample's
densities by Levenberg–Marquardt through the same engine.

Rows (density metrics over true boxes, the k-th decoded box against the k-th true box
from the bottom; `docs/inference.md` says how +Sample and +Refine rank slots):
  PPD             the network's per-box slot scores;
  PPD+Sample      slots ranked by the best selection objective of a sample that has them
                  (`sampling.selection_objective`; the paper: the trajectory distance);
  PPD+Sample+Refine  slots ranked by closeness to the refined continuous density;
  PPD+Fit..., PPD+Fit(depth)...  the same on boxes fitted to the voxels (`fit`), or to
                  the voxels and then the depth image (`depth`); refinement starts from
                  the most precise boxes evaluated (depth, else voxels, else the network's);
  PPD+Fit(depth)+Est...  with a density estimator (`ppdjax.nn.estimator`): the same
                  boxes scored by the network's and the estimator's log-probabilities
                  together (`combine_logits`); it is then the group refinement starts
                  from (under that prior when refine_prior > 0); "Estimator" is its
                  arg-max alone;
  ...+Sample+Joint  with `joint`: faces and densities fitted together from the same start
                  as +Refine (`joint.refine_joint`; with depth, on the depth image too);
  Frequent, Nearest, Oracle (`ppdjax.eval.baselines`), on the true shape.
MAE: the paper's trajectory MAE in mm (`metrics.trajectory_mae`). Batch records saved as
they are made (`partial`) are reused by a later call: long evaluations resume.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import hashlib
import os
import time

import jax
import numpy as np
from flax import nnx
from tqdm.auto import tqdm

from ppdjax.conventions import OBS_KEYS, PUSH_MAGNITUDES
from ppdjax.dataset import storage
from ppdjax.configs import schema
from ppdjax.configs.schema import EvalConfig
from ppdjax.eval import baselines, partial
from ppdjax.eval.batches import evaluation_objects, read_ahead, table4_batches
from ppdjax.infer.config import DecomposeConfig
from ppdjax.eval.candidates import shape_pool
from ppdjax.eval.evaluator import Evaluator, headline_row
from ppdjax.report.tables import PREFIXES, SELECTION_HORIZONS, model_switches, summarize
from ppdjax.sim.rollout_mjx import settings_for
from ppdjax.training import checkpoints


# of `rows.batch_records`' layout and what they hold: saved batches of another are not
# reused (4: Table 4's shape pool drawn by `stream.sample_towers_jax`; 5: Table 4's rows
# recorded only on the batches that simulate its baselines, `table4_objects`; 6: the
# studies' sweeps only when asked, +Refine falls back to the +Sample answer as decompose)
RECORDS_VERSION = 6


def _weights_hash(model) -> str:
  """sha1 of a model's parameters: which model saved batch records (`partial`)."""
  h = hashlib.sha1()
  for leaf in jax.tree.leaves(nnx.state(model, nnx.Param)):
    h.update(np.asarray(leaf).tobytes())
  return h.hexdigest()


def eval_settings(config, **overrides) -> EvalConfig:
  """The typed `eval` section of a run's (or preset's) config, with `overrides` (keys of
  `schema.EvalConfig`) applied; ConfigError names an unknown or ill-typed one."""
  section = dict(config.eval) if config is not None else {}
  section.update(overrides)
  return schema._section("eval", section)  # pylint: disable=protected-access


def evaluate(trained, data_dir: str, settings: EvalConfig | None = None, *,
             split: str = "test", max_objects: int = 0, subset: str = "first",
             progress: bool = True, partial_dir: str = "", max_seconds: float = 0.0,
             prefetch: bool = True, devices=None, ahead: bool = False,
             **overrides) -> dict:
  """Evaluates a trained model (a workdir or (model, config)); returns the results dict.

  Args:
    trained: a workdir or export, or (model, config).
    data_dir: a generated dataset.
    settings: the typed `eval` section (`schema.EvalConfig`): `decompose`'s settings
      (`DecomposeConfig.from_eval`: the row `decompose` returns, `results["headline"]`)
      and what the tables add (baselines, true boxes, +Joint, Table 4's coverage, the
      studies' sweeps). None: the model's saved section; `overrides` (its keys) win.
    split: the split evaluated.
    max_objects: evaluate only N objects (0: all); `subset` picks the first N ("first") or
      N spread evenly over the split ("spread": many towers, since a tower's
      configurations are stored together).
    progress: a progress bar.
    partial_dir: saves each batch's records as it is made and reuses those a previous
      call with the same settings saved (`partial.PartialRecords`); with `max_seconds` > 0
      the call stops after the batch that passes it and raises `partial.EvaluationPaused`.
    prefetch: read the next batch in a background thread while the current one computes.
    devices: the local devices each batch splits over (None: all; the batch is padded).
    ahead: compile the stages ahead of time on the first batch's shapes and return (with
      JAX's persistent compilation cache on, an evaluation with these settings of a model
      of the same configuration then loads its programs instead of compiling them).

  `results["seconds_by_part"]`: where this call's time went. +Sample selects by
  `sampling.selection_objective` over the first `selection_horizon` steps; +Refine starts
  from the candidate closest over all steps. With `studies`, `results["prior_sweeps"]`
  (every τ of PRIOR_WEIGHTS), the posterior temperatures, the screens and
  `results["oracle_pick"]` (each +Sample row's ceiling on its own candidates); with
  `horizon_sweep`, `results["selection_sweeps"]` too. `table4_objects` > 0: Table 4's
  sampling baselines on whole batches spread over the objects (at least this many).

  Raises:
    CheckpointError for a workdir without a checkpoint, DatasetError for a dataset
    without the split, ConfigError for an unknown or ill-typed setting,
    partial.OtherEvaluation for a `partial_dir` of another evaluation, EvaluationPaused
    when `max_seconds` ran out first.
  """
  t_start = time.perf_counter()
  # the settings and the dataset checked before the model loads: a bad one is named at once
  config = checkpoints.read_config(trained) if isinstance(trained, str) else trained[1]
  e = eval_settings(config if settings is None else None, **{
      **(dataclasses.asdict(settings) if settings is not None else {}), **overrides})
  decompose = DecomposeConfig.from_eval(dataclasses.asdict(e))
  samples, joint, seed = e.samples, e.joint, e.seed
  with_baselines, studies = e.baselines, e.studies or e.horizon_sweep
  if e.selection_horizon not in SELECTION_HORIZONS:
    raise schema.ConfigError(f"selection_horizon must be one of {SELECTION_HORIZONS} (the "
                             f"distances the evaluation computes; 0: all steps), got "
                             f"{e.selection_horizon}")
  test = storage.open_dataset(data_dir, split)
  model, config = checkpoints.load(trained) if isinstance(trained, str) else trained
  objects = evaluation_objects(len(test), max_objects, subset)
  n = len(objects)
  batch_size = max(1, min(e.batch_size, n))
  # a batch splits over the devices: pad it to a multiple
  num_devices = len(devices) if devices is not None else jax.local_device_count()
  batch_size = -(-batch_size // num_devices) * num_devices
  settings = {**dataclasses.asdict(e), "batch_size": batch_size,
              "table4_objects": e.table4_objects if with_baselines else 0}
  starts = range(0, n, batch_size)
  table4_starts = {starts[i] for i in table4_batches(
      [min(batch_size, n - x) for x in starts], settings["table4_objects"])}
  if max_seconds and not partial_dir:
    raise ValueError("max_seconds needs partial_dir: where the batches done are kept")
  saved = (partial.PartialRecords(partial_dir, {
      **settings, "weights": _weights_hash(model),
      "estimator": os.path.abspath(e.estimator) if e.estimator else "",
      "data": os.path.abspath(data_dir), "split": split,
      "objects": hashlib.sha1(objects.tobytes()).hexdigest(), "records": RECORDS_VERSION,
      "backend": jax.default_backend()})
           if partial_dir else None)
  computed = 0  # batches this call computed (a call that pauses has made progress)
  table4_after = 0  # of them after the first, those that simulated Table 4's baselines
  ev = train = None  # built (and compiled) only if a batch is not saved
  prefixes = sorted({p for p in PREFIXES if p <= samples} | {samples})
  records = collections.defaultdict(list)
  key = jax.random.key(seed)
  parts = collections.Counter()  # seconds: read (waited for), baselines, device, records
  clock = time.perf_counter
  bar = tqdm(total=n, desc="evaluating", unit="object", disable=not progress)
  keys_read = OBS_KEYS + ("primitives", "materials") + (
      ("depth",) if decompose.fit.depth else ()) + tuple(  # each object's pushes, if recorded
          k for k in (PUSH_MAGNITUDES,) if k in test.sample_keys)

  def read(start):
    """A batch's saved records, or its observations (padded to the batch size: one
    compiled shape) and true slots."""
    idx = objects[start:start + batch_size]
    rec = saved.load(start) if saved else None
    if rec is not None:
      return len(idx), rec, None, None
    batch = test.take(np.pad(idx, (0, batch_size - len(idx)), mode="edge"), keys=keys_read)
    # the host's share of a batch, made here so that reading ahead hides it
    pool = (shape_pool(jax.random.fold_in(key, start), samples,
                       batch["primitives"].density.shape[-1])
            if with_baselines and start in table4_starts else None)
    return len(idx), None, (batch, pool), (baselines.true_slots(batch["primitives"]),
                                           baselines.true_materials(batch["primitives"],
                                                                    batch["materials"]))

  def make_records(start, keep, out, labels, base):
    """A computed batch's records, saved; made in a background thread while the next
    batch runs on the device. `labels`: the true (slots, material ids), bottom to top."""
    t = clock()
    slot, material = labels
    rec = ev.records(out, slot[:keep], slot[:keep] >= 0,
                     None if base is None else base[:keep], prefixes=prefixes,
                     table4=start in table4_starts, studies=studies,
                     horizon_sweep=e.horizon_sweep)
    rec[("true_material",)] = material[:keep]  # the by-material scores (`tables.summarize`)
    if saved:
      saved.save(start, rec)
    return rec, clock() - t

  def add(rec, keep):
    for k, v in rec.items():
      records[k].append(np.asarray(v))
    bar.update(keep)

  pending = []  # (objects, future) of the batch whose records are being made

  def collect():
    """Adds the pending batch's records (batches stay in order)."""
    for keep, future in pending:
      t = clock()
      rec, seconds = future.result()
      parts["records_waited"] += clock() - t
      parts["records"] += seconds
      add(rec, keep)
    pending.clear()

  with concurrent.futures.ThreadPoolExecutor(1) as behind:
    for start, (keep, rec, read_batch, labels) in read_ahead(read, starts, prefetch):
      batch, pool = read_batch if read_batch is not None else (None, None)
      t = clock()
      if rec is None:
        if ev is None:  # the training split (Nearest's) is read while the stages compile
          reading = behind.submit(baselines.TrainingSet, storage.open_dataset(data_dir, "train"),
                                  progress=False) if with_baselines and not ahead else None
          ev = Evaluator(model, config, decompose, baselines_on=with_baselines,
                         camera=test.camera if decompose.fit.with_ else None, joint=joint,
                         true_shapes=e.true_shapes, pushes=test.pushes,
                         settings=settings_for(test.engine),
                         table4_every_batch=table4_starts == set(starts), devices=devices)
          t = clock()  # the first batch's device time includes compiling every stage
          if ahead:  # compiled ahead of time into JAX's persistent cache, and no more
            ev.compile(batch, jax.random.fold_in(key, start), pool, execute=False)
            bar.close()
            return {"compiled_ahead": True, **settings,
                    "seconds": round(time.perf_counter() - t_start, 1),
                    "compile_seconds": round(ev.seconds["compile"], 1)}
          if not ev.compiled:  # every stage at once (on an accelerator)
            ev.compile(batch, jax.random.fold_in(key, start), pool)
          parts["device"] += clock() - t
          train = reading.result() if reading else None
          t = clock()
        base = (baselines.baseline_scores(train, batch, seed * 1_000_003 + start)
                if with_baselines else None)
        t, parts["baselines"] = clock(), parts["baselines"] + clock() - t
        out = ev.batch(batch, base, jax.random.fold_in(key, start), pool,
                       table4=start in table4_starts)
        out = jax.tree.map(lambda x: x[:keep], out)
        parts["device"] += clock() - t
        if not computed:  # the stages' seconds after the first batch (its compilation)
          first = dict(ev.seconds, device=parts["device"], wall=clock() - t_start)
        else:
          table4_after += start in table4_starts
        collect()  # the previous batch's, made while this one ran on the device
        pending.append((keep, behind.submit(make_records, start, keep, out, labels, base)))
        computed += 1
      else:
        collect()
        add(rec, keep)
      if (max_seconds and computed and start + keep < n
          and time.perf_counter() - t_start > max_seconds):
        collect()
        bar.close()
        raise partial.EvaluationPaused(start + keep, n, partial_dir)
    collect()
  bar.close()
  # intervals resample whole towers or tools: their configurations share one shape
  geometries = test.take(objects, keys=("tower_id",))["tower_id"]
  results = summarize(model_switches(config), {k: np.concatenate(v) for k, v in records.items()},
                      geometries)
  results["table4_evaluated"] = sum(len(r) for r in records.get(("prefix", "PPD", prefixes[0]), []))
  results.update({
      "workdir": trained if isinstance(trained, str) else None, "data": data_dir,
      "split": split, "objects": int(n), **settings,
      "data_kind": test.kind,  # what a geometry is, for the reports' interval notes
      "headline": headline_row(decompose),
      "decompose": decompose.to_dict(), "subset": subset,
      "devices": num_devices, "seconds": round(time.perf_counter() - t_start, 1),
      "seconds_by_part": {"read": round(read.waited, 1),
                          **{k: round(v, 1) for k, v in parts.items()}}})
  if train is not None:  # Frequent's one slot for every box (unknown to a call that only resumed)
    results["frequent_slot"] = int(np.argmax(train.frequency_scores()))
  if computed:
    # where the device time of a batch goes once compiled: per jitted stage
    after = {k: v - first.get(k, 0.0) for k, v in ev.seconds.items() if k != "compile"}
    after["host"] = parts["device"] - first["device"] - sum(after.values())  # the rest
    results["seconds_by_stage"] = {
        "first_batch": round(first["device"], 1), "batches_after_first": computed - 1,
        "compile": round(ev.seconds["compile"], 1),  # of the first batch: every stage at once
        "table4_batches_after_first": table4_after,
        "first_batch_wall": round(first["wall"], 1),  # from the call's start
        "after_first": {k: round(v, 2) for k, v in after.items()}}
  return results
