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
import functools
import hashlib
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from tqdm.auto import tqdm

from ppdjax.conventions import (NUM_DENSITY_SLOTS, OBS_KEYS, slot_to_density,
                                slot_to_density_jax)
from ppdjax.dataset import storage
from ppdjax.infer import baselines, partial, rows, sampling
from ppdjax.infer.batches import evaluation_objects, read_ahead
from ppdjax.infer.groups import candidate_layout, decode_groups, fit_groups
from ppdjax.infer.joint import joint_batch
from ppdjax.infer.refine import refine_batch
from ppdjax.infer.tables import (BASELINES, PREFIXES, SELECTION_HORIZONS, model_switches,
                                 summarize)
from ppdjax.primitives import bottom_to_top
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, settings_for
from ppdjax.training import checkpoints, sharding
from ppdjax.training import estimator as estimator_module


def simultaneous_candidates() -> int:
  """Candidates simulated at once (objects × candidates; × 4 pushes in rollouts): 16,384
  on an accelerator (65,536 rollouts run at ~10× the rate of 2,048, benchmarks.md), 2,048
  on a CPU."""
  return 2048 if jax.default_backend() == "cpu" else 16384


def _simulate(pred, fitted, logits, fit_logits, true, base_slots, pool, obs_traj, keys, *,
              samples, with_baselines, chunk, pushes, settings):
  """Per object: (distance (C, H) over each of SELECTION_HORIZONS, MAE (C,)) of every
  candidate (`candidate_layout`), the network's
  candidate slots on its boxes, and a tuple of them on each of `fitted` (a tuple of the
  fit groups' boxes, in layout order, scored by `fit_logits`, a tuple alike). `keys`
  (B, 4): each object's own, so that a batch split over devices draws the same."""
  k = pred.density.shape[-1]

  def one(args):
    p, fs, lg, flg, t, bs, traj, kk = args
    slots, _ = sampling.candidate_slots(lg, p.valid, samples, kk[0])
    cands = [sampling.with_slots(p, slots)]
    fit_slots = []
    for f, fl in zip(fs, flg):  # one key for every fit group: rows with the same scores
      # differ by the boxes alone
      fit_slots.append(sampling.candidate_slots(fl, f.valid, samples, kk[3])[0])
      cands.append(sampling.with_slots(f, fit_slots[-1]))
    if with_baselines:
      uniform, _ = sampling.candidate_slots(jnp.zeros_like(lg), t.valid, samples, kk[1],
                                            include_mode=False)
      shape_slots = jax.random.randint(kk[2], (samples, k), 0, NUM_DENSITY_SLOTS)
      cands += [sampling.with_slots(t, uniform),
                pool.replace(density=slot_to_density_jax(shape_slots)),
                sampling.with_slots(t, bs)]
    cands = jax.tree.map(lambda *x: jnp.concatenate(x), *cands)
    dist, mae = sampling.score_candidates(cands, traj, pushes, settings,
                                          horizons=SELECTION_HORIZONS)
    return dist, mae, slots, tuple(fit_slots)

  return jax.lax.map(one, (pred, fitted, logits, fit_logits, true, base_slots, obs_traj, keys),
                     batch_size=chunk)


# +Refine and +Joint start from the sample closest in trajectory, whatever τ the +Sample
# rows use: on the validation split of unseen towers that start refined best (top-1 62.6 %
# against 59.9 % from τ = 0.05; experiments/results/prior_study_val.md).
REFINE_FROM_TAU = 0.0
RECORDS_VERSION = 3  # of `rows.batch_records`' layout: saved batches of another are not reused


_log_priors = jax.jit(jax.vmap(sampling.log_prior))  # (B, S) of each object's candidates


def shape_pool(key, samples: int, num_slots: int):
  """Table 4's "Sample Phys.+Shape" pool for one batch: `samples` random tower shapes
  (`baselines.random_shapes`) seeded from the batch's key."""
  return baselines.random_shapes(int(jax.random.randint(key, (), 0, 2**31 - 1)), samples,
                                 num_slots=num_slots)


def _weights_hash(model) -> str:
  """sha1 of a model's parameters: which model saved batch records (`partial`)."""
  h = hashlib.sha1()
  for leaf in jax.tree.leaves(nnx.state(model, nnx.Param)):
    h.update(np.asarray(leaf).tobytes())
  return h.hexdigest()


class Evaluator:
  """Compiles the per-batch calls once for a model, batch size and sample count."""

  def __init__(self, model, config, *, samples: int, refine: bool, refine_steps: int = 12,
               baselines_on: bool = True, fit: bool = False,
               depth: bool = False, camera: dict | None = None, refine_prior: float = 0.0,
               estimator=None, estimator_weight: float = 1.0, joint: bool = False,
               true_shapes: bool = False, pushes=None, settings=DEFAULT_SETTINGS):
    if samples < 1:
      raise ValueError(f"samples must be >= 1, got {samples}")
    if depth and camera is None:
      raise ValueError("the +Fit(depth) rows need the depth images' camera "
                       "(storage.Dataset.camera)")
    self.config, self.samples, self.refine, self.joint = config, samples, refine, joint
    self.fits = fit_groups(fit, depth, estimator is not None)
    if joint and not self.fits:
      raise ValueError("+Joint moves fitted boxes' faces: it needs fit or depth")
    self.baselines_on = baselines_on
    self.seconds = collections.Counter()  # per stage of `batch` (`_timed`)
    pushes = default_pushes() if pushes is None else pushes
    # every group sampled and scored; "true" (the oracle boxes) after the fits
    self.groups = self.fits + (("true",) if true_shapes else ())
    self.layout = candidate_layout(samples, self.groups, baselines_on)
    per_object = max(s.stop for s in self.layout.values())
    chunk = max(1, simultaneous_candidates() // per_object)
    self.graphdef, self.state = nnx.split(model)
    est_graphdef, self.est_state = (nnx.split(estimator) if estimator is not None
                                    else (None, None))
    # each call runs per object: on several local devices, each takes its share of the
    # batch (`sharding.jit_over_local_devices`; the weights and the baselines' shape pool whole)
    per_device = sharding.jit_over_local_devices
    self._decode = per_device(functools.partial(
        decode_groups, self.graphdef, groups=self.fits, camera=camera,
        est_graphdef=est_graphdef, est_weight=estimator_weight, true_shapes=true_shapes),
        replicated=(0, 3))
    self._simulate = per_device(functools.partial(
        _simulate, samples=samples, with_baselines=baselines_on, chunk=chunk, pushes=pushes,
        settings=settings), replicated=(6,))
    # without a fit, the network's boxes are refined as the paper's least squares; with a
    # fit, the fitted boxes, as a MAP step when refine_prior > 0 (the presets: 0)
    self._refine = per_device(functools.partial(
        refine_batch, steps=refine_steps, prior_weight=refine_prior if self.fits else 0.0,
        pushes=pushes, settings=settings))
    # +Joint vectorised over 64 objects at once on an accelerator (a batch of 64 in 4.1 s
    # on an H100, 20.6 s 8 at once: benchmarks.md), 8 on a CPU
    self._joint = per_device(functools.partial(
        joint_batch, steps=refine_steps, prior_weight=refine_prior if self.fits else 0.0,
        camera=camera if depth else None, pushes=pushes, settings=settings,
        at_once=8 if jax.default_backend() == "cpu" else 64))

  def _timed(self, stage: str, fn, *args):
    """fn(*args), waited for, its seconds added to self.seconds[stage] (where a batch's
    time goes: the first batch's include compilation)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    self.seconds[stage] += time.perf_counter() - t
    return out

  def batch(self, batch: dict, base_scores: np.ndarray | None, key, pool=None) -> dict:
    """Per-object arrays for one batch (see `evaluate` for what they become). `pool`:
    Table 4's random tower shapes (`shape_pool`; drawn here from `key` when None)."""
    obs = {k: jnp.asarray(batch[k])
           for k in OBS_KEYS + (("depth",) if "fit_depth" in self.fits else ())}
    true = bottom_to_top(jax.tree.map(jnp.asarray, batch["primitives"]))
    decoded = self._timed("decode", self._decode, self.state, obs, true, self.est_state)
    pred, logits = decoded["pred"], decoded["logits"]
    fitted = tuple(decoded["fitted"][g] for g in self.groups)
    fit_logits = tuple(decoded["group_logits"][g] for g in self.groups)
    b, k = true.density.shape
    base_slots = (np.argmax(base_scores, -1).astype(np.int32) if base_scores is not None
                  else np.zeros((b, len(BASELINES), k), np.int32))
    if pool is None:  # (unused without the baselines: one shape then)
      pool = shape_pool(key, self.samples if self.baselines_on else 1, k)
    dist, mae, slots, fit_slots = self._timed(
        "sample", self._simulate, pred, fitted, logits, fit_logits, true,
        jnp.asarray(base_slots), jax.tree.map(jnp.asarray, pool), obs["trajectories"],
        jax.random.split(key, (b, 4)))
    out = jax.device_get({**decoded, "hdist": dist, "mae": mae, "slots": slots})
    out["dist"] = out["hdist"][..., SELECTION_HORIZONS.index(0)]  # the whole trajectory
    out["logp"] = np.asarray(_log_priors(logits, slots, pred.valid))
    out["fit_slots"] = {g: np.asarray(s) for g, s in zip(self.groups, fit_slots)}
    out["fit_logp"] = {g: np.asarray(_log_priors(fl, s, f.valid))
                       for g, s, f, fl in zip(self.groups, fit_slots, fitted, fit_logits)}
    if self.refine or self.joint:  # from the closest sample, on the most precise boxes
      group = self.fits[-1] if self.fits else "ppd"
      prims, prior, d0, m0 = self._best_sample(out, decoded, group, REFINE_FROM_TAU)
      if self.refine:
        out["refine"] = jax.device_get(self._timed("refine", self._refine, prims, prior,
                                                   obs["trajectories"], d0, m0))
        out["refine"]["sample_dist"] = d0  # the start's distance
      if self.joint:
        depth = obs["depth"].astype(jnp.float32) if "depth" in obs else jnp.zeros((len(d0),))
        out["joint"] = jax.device_get(self._timed("joint", self._joint, prims, prior,
                                                  obs["trajectories"], depth, true))
    if self.refine and "true" in self.groups:  # the oracle column refined alike
      prims, prior, d0, m0 = self._best_sample(out, decoded, "true", REFINE_FROM_TAU)
      out["refine_true"] = jax.device_get(self._timed("refine", self._refine, prims, prior,
                                                      obs["trajectories"], d0, m0))
    return out

  def _best_sample(self, out: dict, decoded: dict, group: str, tau: float):
    """A group's best candidate (by the +Sample objective at `tau`) as boxes with its
    densities, the group's logits (the MAP prior), and its distance and MAE."""
    fitted = group != "ppd"
    boxes = decoded["fitted"][group] if fitted else decoded["pred"]
    cand_slots = out["fit_slots"][group] if fitted else out["slots"]
    d, m = out["dist"][:, self.layout[group]], out["mae"][:, self.layout[group]]
    logp = out["fit_logp"][group] if fitted else out["logp"]
    best = np.argmin(sampling.selection_objective(d, logp, tau), -1)
    start = np.take_along_axis(cand_slots, best[:, None, None], 1)[:, 0]
    prims = boxes.replace(density=jnp.asarray(slot_to_density(start), jnp.float32))
    rows = np.arange(len(best))
    prior = decoded["group_logits"][group] if fitted else decoded["logits"]
    return prims, prior, d[rows, best], m[rows, best]


EVAL_SETTINGS = ("samples", "refine", "refine_steps", "batch_size", "prior_weight", "fit",
                 "depth", "refine_prior", "estimator", "estimator_weight", "joint",
                 "true_shapes", "selection_horizon")


def eval_settings(config, **overrides) -> dict:
  """`evaluate`'s settings from a preset's `eval` section; overrides that are not None win."""
  defaults = {"fit": False, "depth": False, "refine_prior": 0.0, "estimator": "",
              "estimator_weight": 1.0, "joint": False,
              "true_shapes": False, "selection_horizon": 0}  # older presets lack them
  out = {k: config.eval.get(k, defaults.get(k)) for k in EVAL_SETTINGS}
  unknown = sorted(set(overrides) - set(EVAL_SETTINGS))
  if unknown:
    raise ValueError(f"unknown evaluation settings {unknown}; expected {EVAL_SETTINGS}")
  out.update({k: v for k, v in overrides.items() if v is not None})
  return out


def evaluate(trained, data_dir: str, *, split: str = "test", samples: int = 512,
             refine: bool = False, refine_steps: int = 12, batch_size: int = 16,
             max_objects: int = 0, with_baselines: bool = True, seed: int = 0,
             prior_weight: float = 0.0, subset: str = "first", fit: bool = False,
             depth: bool = False, refine_prior: float = 0.0, estimator: str = "",
             estimator_weight: float = 1.0, joint: bool = False, true_shapes: bool = False,
             selection_horizon: int = 0, horizon_sweep: bool = False, progress: bool = True,
             partial_dir: str = "", max_seconds: float = 0.0, prefetch: bool = True) -> dict:
  """Evaluates a trained model (a workdir or (model, config)); returns the results dict.

  +Sample selects by `sampling.selection_objective` with τ = prior_weight;
  `results["prior_sweeps"][row]` scores each +Sample row's selection (and
  `results["prior_sweep"]` PPD+Sample's, as before) for every τ in PRIOR_WEIGHTS (free:
  the candidates are simulated once). +Sample's rows select on the distance over the first
  `selection_horizon` steps (0: all, the paper's); `horizon_sweep` also records the τ
  sweep at every horizon of SELECTION_HORIZONS (`results["selection_sweeps"][row][h][τ]`).
  Choose τ and the horizon on the validation split. `results["oracle_pick"][row]`: the
  row's ceiling on its own candidates (`rows.oracle_pick`). `results["seconds_by_part"]`:
  where this call's time went (waiting for batches to be read, the baselines' scores, the
  jitted calls with their compilation, the records). With
  `max_objects`, `subset` picks the first N objects ("first") or N spread evenly over the
  split ("spread": many towers, since a tower's 8 configurations are stored together).
  `fit` adds the +Fit rows (boxes fitted to the voxels), `depth` the +Fit(depth) rows
  (then refined against the dataset's depth images, through its camera). `estimator` (a
  folder `ppdjax.train_estimator` wrote) adds the +Est rows on the most precise fitted
  boxes, its log-probabilities weighted by `estimator_weight` beside the network's.
  `true_shapes` adds the oracle rows "PPD+True boxes" (+Sample, +Sample+Refine): the
  network's k-th density scores on the k-th true box, sampled and refined alike.
  `partial_dir` saves each batch's records as it is made and reuses those a previous call
  with the same settings saved (`partial.PartialRecords`); with `max_seconds` > 0 the call
  stops after the batch that passes it and raises `partial.EvaluationPaused`. `prefetch`
  reads the next batch in a background thread while the current one computes.

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
  devices = jax.local_device_count()  # a batch splits over them: pad it to a multiple
  batch_size = -(-batch_size // devices) * devices
  settings = {"samples": samples, "refine": refine, "refine_steps": refine_steps,
              "batch_size": batch_size, "baselines": with_baselines, "seed": seed,
              "prior_weight": prior_weight, "fit": fit, "depth": depth,
              "refine_prior": refine_prior if (fit or depth) and refine else 0.0,
              "estimator": estimator, "estimator_weight": estimator_weight if estimator else 0.0,
              "joint": joint, "true_shapes": true_shapes, "selection_horizon": selection_horizon,
              "horizon_sweep": horizon_sweep}
  if selection_horizon not in SELECTION_HORIZONS:
    raise ValueError(f"selection_horizon must be one of {SELECTION_HORIZONS} (0: all steps), "
                     f"got {selection_horizon}")
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
                       batch["primitives"].density.shape[-1]) if with_baselines else None)
    return len(idx), None, (batch, pool), baselines.true_slots(batch["primitives"])

  for start, (keep, rec, read_batch, slot) in read_ahead(read, range(0, n, batch_size),
                                                         prefetch):
    batch, pool = read_batch if read_batch is not None else (None, None)
    t = clock()
    if rec is None:
      if ev is None:
        train = baselines.TrainingSet(storage.open_dataset(data_dir, "train"),
                                      progress=progress) if with_baselines else None
        ev = Evaluator(model, config, samples=samples, refine=refine,
                       refine_steps=refine_steps, baselines_on=with_baselines, fit=fit,
                       depth=depth, camera=test.camera if depth else None,
                       refine_prior=refine_prior,
                       estimator=estimator_module.load(estimator)[0] if estimator else None,
                       estimator_weight=estimator_weight, joint=joint, true_shapes=true_shapes,
                       pushes=test.pushes, settings=settings_for(test.engine))
        t = clock()
      base = (baselines.baseline_scores(train, batch, seed * 1_000_003 + start)
              if with_baselines else None)
      t, parts["baselines"] = clock(), parts["baselines"] + clock() - t
      out = ev.batch(batch, base, jax.random.fold_in(key, start), pool)
      out = jax.tree.map(lambda x: x[:keep], out)
      t, parts["device"] = clock(), parts["device"] + clock() - t
      if not computed:  # the stages' seconds after the first batch (its compilation)
        first = dict(ev.seconds, device=parts["device"])
      rec = rows.batch_records(out, slot[:keep], slot[:keep] >= 0,
                               None if base is None else base[:keep], samples=samples,
                               prior_weight=prior_weight, prefixes=prefixes,
                               with_baselines=with_baselines, refine=refine, layout=ev.layout,
                               selection_horizon=selection_horizon,
                               horizon_sweep=horizon_sweep)
      parts["records"] += clock() - t
      if saved:
        saved.save(start, rec)
      computed += 1
    for k, v in rec.items():
      records[k].append(np.asarray(v))
    bar.update(keep)
    if (max_seconds and computed and start + keep < n
        and time.perf_counter() - t_start > max_seconds):
      bar.close()
      raise partial.EvaluationPaused(start + keep, n, partial_dir)
  bar.close()
  results = summarize(model_switches(config), {k: np.concatenate(v) for k, v in records.items()})
  results.update({
      "workdir": trained if isinstance(trained, str) else None, "data": data_dir,
      "split": split, "objects": int(n), **settings,
      "refine_steps": refine_steps if refine else 0, "subset": subset,
      "seconds": round(time.perf_counter() - t_start, 1),
      "seconds_by_part": {"read": round(read.waited, 1),
                          **{k: round(v, 1) for k, v in parts.items()}}})
  if computed:
    # where the device time of a batch goes once compiled: per jitted stage
    after = {k: v - first.get(k, 0.0) for k, v in ev.seconds.items()}
    after["host"] = parts["device"] - first["device"] - sum(after.values())  # the rest
    results["seconds_by_stage"] = {
        "first_batch": round(first["device"], 1), "batches_after_first": computed - 1,
        "after_first": {k: round(v, 2) for k, v in after.items()}}
  return results
