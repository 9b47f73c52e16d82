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
  Frequent, Nearest, Oracle (`ppdjax.infer.baselines`), on the true shape.
MAE: the paper's trajectory MAE in mm (`metrics.trajectory_mae`). Batch records saved as
they are made (`partial`) are reused by a later call: long evaluations resume.
"""

from __future__ import annotations

import collections
import concurrent.futures
import hashlib
import os
import time

import jax
import numpy as np
from flax import nnx
from tqdm.auto import tqdm

from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import storage
from ppdjax.infer import baselines, faces, partial, rows
from ppdjax.infer.batches import evaluation_objects, read_ahead, table4_batches
from ppdjax.infer.evaluator import REFINE_FROM_TAU, Evaluator, shape_pool
from ppdjax.infer.refine import check_jacobian
from ppdjax.infer.tables import PREFIXES, check_horizon, model_switches, summarize
from ppdjax.sim.rollout_mjx import settings_for
from ppdjax.training import checkpoints
from ppdjax.training import estimator as estimator_module


# of `rows.batch_records`' layout and what they hold: saved batches of another are not
# reused (4: Table 4's shape pool drawn by `stream.sample_towers_jax`; 5: Table 4's rows
# recorded only on the batches that simulate its baselines, `table4_objects`)
RECORDS_VERSION = 5


def _weights_hash(model) -> str:
  """sha1 of a model's parameters: which model saved batch records (`partial`)."""
  h = hashlib.sha1()
  for leaf in jax.tree.leaves(nnx.state(model, nnx.Param)):
    h.update(np.asarray(leaf).tobytes())
  return h.hexdigest()


EVAL_SETTINGS = ("samples", "refine", "refine_steps", "batch_size", "prior_weight", "fit",
                 "depth", "refine_prior", "estimator", "estimator_weight", "joint",
                 "true_shapes", "selection_horizon", "refine_jacobian", "table4_objects",
                 "face_spread", "image_fit", "refine_horizon")


def eval_settings(config, **overrides) -> dict:
  """`evaluate`'s settings from a preset's `eval` section; overrides that are not None win."""
  defaults = {"fit": False, "depth": False, "refine_prior": 0.0, "estimator": "",
              "estimator_weight": 1.0, "joint": False,
              "true_shapes": False, "selection_horizon": 0,
              "refine_jacobian": "forward", "table4_objects": 0,
              "face_spread": 0.0, "image_fit": False,
              "refine_horizon": 0}  # older presets lack them
  out = {k: config.eval.get(k, defaults.get(k)) for k in EVAL_SETTINGS}
  unknown = sorted(set(overrides) - set(EVAL_SETTINGS))
  if unknown:
    raise ValueError(f"unknown evaluation settings {unknown}; expected {EVAL_SETTINGS}")
  out.update({k: v for k, v in overrides.items() if v is not None})
  if overrides.get("image_fit") is None:  # the preset's image fit goes with its fit
    out["image_fit"] = bool(out["image_fit"] and out["fit"])
  return out


def evaluate(trained, data_dir: str, *, split: str = "test", samples: int = 512,
             refine: bool = False, refine_steps: int = 12, batch_size: int = 16,
             max_objects: int = 0, with_baselines: bool = True, seed: int = 0,
             prior_weight: float = 0.0, subset: str = "first", fit: bool = False,
             depth: bool = False, refine_prior: float = 0.0, estimator: str = "",
             estimator_weight: float = 1.0, joint: bool = False, true_shapes: bool = False,
             selection_horizon: int = 0, horizon_sweep: bool = False,
             refine_jacobian: str = "forward", table4_objects: int = 0,
             face_spread: float = 0.0, image_fit: bool = False, refine_horizon: int = 0,
             progress: bool = True,
             partial_dir: str = "", max_seconds: float = 0.0, prefetch: bool = True,
             devices=None, ahead: bool = False) -> dict:
  """Evaluates a trained model (a workdir or (model, config)); returns the results dict.

  +Sample selects by `sampling.selection_objective` with τ = prior_weight;
  `results["prior_sweeps"][row]` scores each +Sample row's selection (and
  `results["prior_sweep"]` PPD+Sample's, as before) for every τ in PRIOR_WEIGHTS (free:
  the candidates are simulated once). +Sample's rows select on the distance over the first
  `selection_horizon` steps (0: all, the paper's); `horizon_sweep` also records the τ
  sweep at every horizon of SELECTION_HORIZONS (`results["selection_sweeps"][row][h][τ]`).
  Choose τ and the horizon on the validation split. +Refine and +Joint start from the
  candidate closest over the first `refine_horizon` steps (0: all; `Evaluator`).
  `results["oracle_pick"][row]`: the row's ceiling on its own candidates
  (`rows.oracle_pick`). `results["seconds_by_part"]`: where this call's time went
  (waiting for batches to be read, the baselines' scores, the jitted calls with their
  compilation, the records, which a background thread makes while the next batch
  computes, and the time waited for them). With
  `max_objects`, `subset` picks the first N objects ("first") or N spread evenly over the
  split ("spread": many towers, since a tower's 8 configurations are stored together).
  `fit` adds the +Fit rows (boxes fitted to the voxels, and with `image_fit` then to the
  edges of the dataset's images, through its camera: `image_fit`), `depth` the +Fit(depth)
  rows (the voxel fit refined against the dataset's depth images instead). `estimator` (a
  folder `ppdjax.train_estimator` wrote) adds the +Est rows on the most precise fitted
  boxes, its log-probabilities weighted by `estimator_weight` beside the network's.
  `refine_jacobian` is how +Refine takes its Jacobian (`refine.check_jacobian`: forward
  mode, or differences, 3x faster through the GPU kernel).
  `table4_objects` > 0: Table 4's sampling baselines (2 × `samples` candidates an object,
  40 % of a batch's rollouts at 512 samples with both fits) are simulated on whole batches
  spread over the objects, at least this many objects, and Table 4 is reported on those
  (`results["table4_evaluated"]` objects); 0: on every object.
  `face_spread` (voxels) > 0: the +Fit+Sample candidates' faces are drawn too, within this
  of the fitted ones (`faces.spread_faces`; where the voxels allow them at 0.5).
  `true_shapes` adds the oracle rows "PPD+True boxes" (+Sample, +Sample+Refine): the
  network's k-th density scores on the k-th true box, sampled and refined alike.
  `partial_dir` saves each batch's records as it is made and reuses those a previous call
  with the same settings saved (`partial.PartialRecords`); with `max_seconds` > 0 the call
  stops after the batch that passes it and raises `partial.EvaluationPaused`. `prefetch`
  reads the next batch in a background thread while the current one computes. `devices`:
  the local devices each batch splits over (None: all; the batch is padded to a multiple).
  `ahead`: compile the stages ahead of time on the first batch's shapes and return (no
  batch is evaluated; the weights and a batch are placed on the device, and XLA may run
  kernels there to tune them); with JAX's persistent compilation cache on,
  the evaluation with these settings of a model of the same configuration (any weights)
  then loads its programs instead of compiling them (`Evaluator.compile(execute=False)`);
  returns the settings and "compile_seconds".

  Raises:
    CheckpointError for a workdir without a checkpoint, DatasetError for a dataset
    without the split, partial.OtherEvaluation for a `partial_dir` of another evaluation,
    EvaluationPaused when `max_seconds` ran out first.
  """
  t_start = time.perf_counter()
  model, config = checkpoints.load(trained) if isinstance(trained, str) else trained
  test = storage.open_dataset(data_dir, split)
  objects = evaluation_objects(len(test), max_objects, subset)
  n = len(objects)
  batch_size = max(1, min(batch_size, n))
  # a batch splits over the devices: pad it to a multiple
  num_devices = len(devices) if devices is not None else jax.local_device_count()
  batch_size = -(-batch_size // num_devices) * num_devices
  settings = {"samples": samples, "refine": refine, "refine_steps": refine_steps,
              "batch_size": batch_size, "baselines": with_baselines, "seed": seed,
              "prior_weight": prior_weight, "fit": fit, "depth": depth,
              "refine_prior": refine_prior if (fit or depth) and refine else 0.0,
              "estimator": estimator, "estimator_weight": estimator_weight if estimator else 0.0,
              "joint": joint, "true_shapes": true_shapes, "selection_horizon": selection_horizon,
              "horizon_sweep": horizon_sweep,
              "refine_jacobian": refine_jacobian if refine else "forward",
              "table4_objects": table4_objects if with_baselines else 0,
              "face_spread": face_spread if fit else 0.0, "image_fit": image_fit,
              "refine_horizon": refine_horizon if refine or joint else 0}
  check_jacobian(refine_jacobian)
  faces.check_spread(face_spread, fit)
  if image_fit and not fit:
    raise ValueError("image_fit refines the +Fit rows' boxes: it needs fit")
  starts = range(0, n, batch_size)
  table4_starts = {starts[i] for i in table4_batches(
      [min(batch_size, n - x) for x in starts], table4_objects)}
  check_horizon("selection_horizon", selection_horizon)
  check_horizon("refine_horizon", refine_horizon)
  if max_seconds and not partial_dir:
    raise ValueError("max_seconds needs partial_dir: where the batches done are kept")
  saved = (partial.PartialRecords(partial_dir, {
      **settings, "weights": _weights_hash(model),
      "estimator": os.path.abspath(estimator) if estimator else "",
      "data": os.path.abspath(data_dir), "split": split,
      "objects": hashlib.sha1(objects.tobytes()).hexdigest(), "records": RECORDS_VERSION,
      "refine_from_tau": REFINE_FROM_TAU, "backend": jax.default_backend()})
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
  keys_read = OBS_KEYS + ("primitives", "materials") + (("depth",) if depth else ())

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
    return len(idx), None, (batch, pool), baselines.true_slots(batch["primitives"])

  def make_records(start, keep, out, slot, base):
    """A computed batch's records, saved; made in a background thread while the next
    batch runs on the device."""
    t = clock()
    rec = rows.batch_records(out, slot[:keep], slot[:keep] >= 0,
                             None if base is None else base[:keep], samples=samples,
                             prior_weight=prior_weight, prefixes=prefixes,
                             with_baselines=with_baselines, refine=refine, layout=ev.layout,
                             selection_horizon=selection_horizon, horizon_sweep=horizon_sweep,
                             table4=start in table4_starts)
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
    for start, (keep, rec, read_batch, slot) in read_ahead(read, starts, prefetch):
      batch, pool = read_batch if read_batch is not None else (None, None)
      t = clock()
      if rec is None:
        if ev is None:  # the training split (Nearest's) is read while the stages compile
          reading = behind.submit(baselines.TrainingSet, storage.open_dataset(data_dir, "train"),
                                  progress=False) if with_baselines and not ahead else None
          ev = Evaluator(model, config, samples=samples, refine=refine,
                         refine_steps=refine_steps, baselines_on=with_baselines, fit=fit,
                         depth=depth, camera=test.camera if depth or image_fit else None,
                         refine_prior=refine_prior,
                         estimator=estimator_module.load(estimator)[0] if estimator else None,
                         estimator_weight=estimator_weight, joint=joint,
                         true_shapes=true_shapes, pushes=test.pushes,
                         settings=settings_for(test.engine), refine_jacobian=refine_jacobian,
                         table4_every_batch=table4_starts == set(starts),
                         face_spread=face_spread, image_fit=image_fit,
                         refine_horizon=settings["refine_horizon"], devices=devices)
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
        pending.append((keep, behind.submit(make_records, start, keep, out, slot, base)))
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
      "refine_steps": refine_steps if refine else 0, "subset": subset,
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
