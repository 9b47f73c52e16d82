"""One batch of an evaluation on the accelerator: decode, fit, sample, simulate, refine.

`Evaluator` compiles the per-batch calls once for a model, batch size and sample count;
`Evaluator.batch` returns the per-object arrays that `rows.batch_records` turns into the
rows of Tables 2, 4 and 5 (`evaluation.evaluate` runs it over a split).
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from ppdjax.conventions import DEPTH_VIDEO, OBS_KEYS, PUSH_MAGNITUDES, slot_to_density
from ppdjax.dataset.depth_video import depth_videos
from ppdjax.infer import sampling
from ppdjax.configs.schema import ConfigError
from ppdjax.infer.config import DecomposeConfig
from ppdjax.infer.decompose import object_keys
from ppdjax.eval.candidates import (shape_pool, simulate_candidates, simulate_table4,
                                    simultaneous_candidates)
from ppdjax.eval.groups import candidate_layout, decode_groups, fit_groups, headline_row
from ppdjax.infer.joint import joint_batch
from ppdjax.infer.refine import refine_batch
from ppdjax.eval.rows import batch_records, screen_mask
from ppdjax.report.tables import BASELINES, SELECTION_HORIZONS, check_horizon
from ppdjax.primitives import bottom_to_top
from ppdjax.sim.pushes import default_pushes, object_magnitudes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, engine_settings, jax_engine
from ppdjax.training import estimator as estimator_module
from ppdjax.training import sharding


_log_priors = jax.jit(jax.vmap(sampling.log_prior))  # (B, S) of each object's candidates


class Evaluator:
  """Compiles the per-batch calls once for a model, batch size and sample count."""

  def __init__(self, model, config, decompose: DecomposeConfig, *, baselines_on: bool = True,
               camera: dict | None = None, joint: bool = False, true_shapes: bool = False,
               pushes=None, settings=DEFAULT_SETTINGS, table4_every_batch: bool = False,
               devices=None):
    """`decompose`: the settings of the row the evaluation reports as `decompose`'s
    (`headline`): its boxes (`fit_stage`), candidates, selection and refinement. `camera`:
    the images' (needed where the fit reads the image or the depth). `devices`: the
    local devices each batch splits over (None: all of them). `table4_every_batch`:
    Table 4's sampling baselines run on every batch, inside the sampling call (one
    program to compile: on a CPU that is a minute less); otherwise in a call of their own
    on the batches `batch` is asked to (`table4=True`)."""
    decompose.validate()
    fit, select, refine = decompose.fit, decompose.select, decompose.refine
    check_horizon("select.horizon", select.horizon)
    if select.screen_steps:
      check_horizon("select.screen_steps", select.screen_steps)
    if select.searches:
      raise ConfigError("select.rounds > 1 and select.inertia (+Search) draw candidates round "
                       "by round: the evaluation's tables replay +Sample's one draw (the "
                       "video study measures +Search: ppdjax.reproduce video)")
    if refine.enabled and refine.starts > 1:
      raise ConfigError("refine.starts > 1 refines several candidates: the evaluation's "
                       "+Refine rows refine the closest one (the video pipeline runs "
                       "several: ppdjax.reproduce video)")
    if select.mass_match:
      raise ConfigError("select.mass_match simulates a second set of candidates: the "
                       "evaluation does not replay it (a study: experiments/mass_match_study)")
    if fit.with_ and camera is None:
      raise ConfigError(f"the fit reads {' and '.join(fit.with_)}: it needs the images' "
                       "camera (storage.Dataset.camera)")
    samples = select.samples
    self.decompose, self.config, self.samples = decompose, config, samples
    # `settings`: the data's JAX engine; the candidates run on decompose's simulator (on a
    # CPU, MuJoCo C), refinement on the JAX engine, as in `decompose`
    settings, jax_settings = engine_settings(decompose.simulator, settings), jax_engine(settings)
    self.refine, self.joint = refine.enabled, joint
    estimator = (estimator_module.load(decompose.estimator.path)[0]
                 if decompose.estimator.path else None)
    estimator_weight = decompose.estimator.weight
    face_spread = fit.face_spread
    self.fits = fit_groups(fit, estimator is not None)
    if joint and not self.fits:
      raise ConfigError("+Joint moves fitted boxes' faces: it needs fit or depth")
    self.baselines_on = baselines_on
    self.seconds = collections.Counter()  # per stage of `batch` (`_timed`)
    pushes = default_pushes() if pushes is None else pushes
    self.pushes = pushes
    # every group sampled and scored; "true" (the oracle boxes) after the fits
    self.groups = self.fits + (("true",) if true_shapes else ())
    self.refine_group = self.fits[-1] if self.fits else "ppd"  # +Refine's and +Joint's boxes
    if face_spread > 0 and (refine.enabled or joint):
      raise ConfigError("fit.face_spread draws the candidates' faces, and +Refine and +Joint "
                       "would start from the fitted ones: with face_spread, no refinement")
    self.layout = candidate_layout(samples, self.groups, baselines_on)
    self.table4_fused = baselines_on and table4_every_batch
    table4 = [self.layout[g] for g in ("uniform", "shapes") if g in self.layout]
    per_object = (table4[0].start if table4 and not self.table4_fused
                  else max(s.stop for s in self.layout.values()))
    chunk = max(1, simultaneous_candidates() // per_object)
    # `compile` before the first batch: on an accelerator (on a CPU, with its few cores, the
    # stages compile no faster side by side, and running the stand-ins costs a batch)
    self.compiled = jax.default_backend() == "cpu"
    # the weights placed without a committed sharding (as restored from a checkpoint they
    # have one): the stages' outputs are then placed alike, whatever made them, and
    # `compile`'s stand-ins match the batches' inputs
    uncommitted = lambda state: jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), state)
    self.graphdef, self.state = nnx.split(model)
    self.state, self.video = uncommitted(self.state), model.video
    est_graphdef, self.est_state = (nnx.split(estimator) if estimator is not None
                                    else (None, None))
    self.est_state = None if estimator is None else uncommitted(self.est_state)
    # each call runs per object: on several local devices, each takes its share of the
    # batch (`sharding.jit_over_local_devices`; the weights and the baselines' shape pool whole)
    per_device = functools.partial(sharding.jit_over_local_devices, devices=devices)
    decode = functools.partial(
        decode_groups, self.graphdef, groups=self.fits, camera=camera, fit=fit,
        est_graphdef=est_graphdef, est_weight=estimator_weight, true_shapes=true_shapes)
    self._decode = per_device(decode, replicated=(0, 3))
    # zeros shaped, typed and placed as the decode's outputs (XLA drops the network), for
    # `compile`'s stand-ins: any difference would make the batches compile again
    self._decode_zeros = per_device(
        lambda *a: jax.tree.map(lambda x: jax.lax.full_like(x, 0), decode(*a)),
        replicated=(0, 3))
    self._simulate = per_device(functools.partial(
        simulate_candidates, samples=samples, with_baselines=baselines_on, chunk=chunk,
        pushes=pushes, settings=settings, face_spreads=tuple(face_spread if g != "true" else 0.0
                                              for g in self.groups),
        ppd_key_is_own=not self.fits),
        replicated=(9,) if self.table4_fused else ())
    self._simulate_table4 = per_device(functools.partial(
        simulate_table4, samples=samples, pushes=pushes, settings=settings,
        chunk=max(1, simultaneous_candidates() // (2 * samples))), replicated=(1,))
    # without a fit, the network's boxes are refined as the paper's least squares; with a
    # fit, the fitted boxes, as a MAP step when refine_prior > 0 (the presets: 0)
    self._refine = per_device(functools.partial(
        refine_batch, steps=refine.steps, prior_weight=refine.prior_weight,
        pushes=pushes, settings=jax_settings, jacobian=refine.jacobian,
        inertia=refine.inertia))
    # +Joint vectorised over 64 objects at once on an accelerator (a batch of 64 in 4.1 s
    # on an H100, 20.6 s 8 at once: benchmarks.md), 8 on a CPU
    self._joint = per_device(functools.partial(
        joint_batch, steps=refine.steps, prior_weight=refine.prior_weight,
        camera=camera if fit.depth else None, pushes=pushes, settings=jax_settings,
        at_once=8 if jax.default_backend() == "cpu" else 64))

  def _timed(self, stage: str, fn, *args):
    """fn(*args), waited for, its seconds added to self.seconds[stage] (where a batch's
    time goes: the first batch's include compilation)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    self.seconds[stage] += time.perf_counter() - t
    return out

  def _inputs(self, batch: dict):
    """The observations (with each object's push magnitudes, "push_magnitudes": the
    dataset's where it records them per object) and the true boxes (bottom to top) of a
    batch, on the device."""
    obs = {k: jnp.asarray(batch[k])
           for k in OBS_KEYS + (("depth",) if "fit_depth" in self.fits else ())}
    obs[PUSH_MAGNITUDES] = object_magnitudes(self.pushes, batch, len(batch["trajectories"]))
    true = jax.tree.map(jnp.asarray, batch["primitives"])
    if self.video is not None:  # the RGB-D row's depth videos, from the true boxes' motion
      obs[DEPTH_VIDEO] = depth_videos(true, obs["trajectories"], *self.video)
    return obs, bottom_to_top(true)

  def _sample_args(self, decoded, true, base_slots, obs, keys, pool) -> tuple:
    """`_simulate`'s arguments for a batch (`compile` makes its stand-ins with it too);
    Table 4's shape `pool` among them when its candidates are simulated there."""
    return (decoded["pred"], tuple(decoded["fitted"][g] for g in self.groups),
            decoded["logits"], tuple(decoded["group_logits"][g] for g in self.groups), true,
            jnp.asarray(base_slots), obs["trajectories"], keys, obs[PUSH_MAGNITUDES]) + (
                (jax.tree.map(jnp.asarray, pool),) if self.table4_fused else ())

  def compile(self, batch: dict, key, pool=None, execute: bool = True) -> None:
    """Compiles every stage for batches shaped like `batch`, all at once: each stage runs
    in its own thread on stand-ins of the shapes it will get (zeros where an earlier stage
    makes its input), and XLA compiles outside the GIL, so this takes about as long as
    the slowest stage's compilation instead of the sum of all (the sampling call and the
    refinement each hold a GPU kernel of 80-100 s to compile; on a CPU `batch` skips it,
    and each stage compiles when first called). Each stage also runs once
    on its stand-ins, all at the same time: the accelerator's memory must hold every
    stage's batch at once (the paper preset's 64 objects ran within an H100's 80 GB).
    `batch` calls it first if it has not run.

    `execute=False` compiles ahead of time instead (`lower(...).compile()` on the stages'
    shapes): no stage runs (XLA may still run kernels on the device to tune them), and
    with JAX's persistent compilation cache on, another process whose Evaluator has the
    same model configuration, batch and settings then loads the programs instead of
    compiling them (`ppdjax.reproduce blocks` compiles the full model's evaluation while it
    trains)."""
    obs, true = self._inputs(batch)
    b, k = true.density.shape
    decoded = (self._decode_zeros(self.state, obs, true, self.est_state) if execute else
               jax.eval_shape(self._decode, self.state, obs, true, self.est_state))
    keys = object_keys(key, b)
    pool = shape_pool(key, self.samples, k) if pool is None and self.baselines_on else pool
    tasks = [(self._decode, (self.state, obs, true, self.est_state)),
             (self._simulate, self._sample_args(decoded, true, np.zeros(
                 (b, len(BASELINES), k), np.int32), obs, keys, pool))]
    if self.baselines_on and not self.table4_fused:
      tasks.append((self._simulate_table4, (true, jax.tree.map(jnp.asarray, pool),
                                            obs["trajectories"], keys, obs[PUSH_MAGNITUDES])))
    if self.refine or self.joint:
      group = self.refine_group
      boxes = decoded["fitted"][group] if self.fits else decoded["pred"]
      prims = boxes.replace(density=jnp.zeros(boxes.density.shape, jnp.float32))
      prior = decoded["group_logits"][group] if self.fits else decoded["logits"]
      zero = np.zeros(b, np.float32)  # the start's distance and MAE, as `batch` has them
      if self.refine:
        tasks.append((self._refine, (prims, prior, obs["trajectories"], zero, zero,
                                     obs[PUSH_MAGNITUDES])))
      if self.joint:
        depth = obs["depth"].astype(jnp.float32) if "depth" in obs else jnp.zeros((b,))
        tasks.append((self._joint, (prims, prior, obs["trajectories"], depth, true,
                                    obs[PUSH_MAGNITUDES])))
    t = time.perf_counter()
    run = ((lambda fn, *args: jax.block_until_ready(fn(*args))) if execute else
           (lambda fn, *args: fn.lower(*args).compile()))
    with concurrent.futures.ThreadPoolExecutor(len(tasks)) as threads:
      for future in [threads.submit(run, fn, *args) for fn, args in tasks]:
        future.result()
    self.seconds["compile"] += time.perf_counter() - t
    self.compiled = execute

  def batch(self, batch: dict, base_scores: np.ndarray | None, key, pool=None,
            table4: bool = True) -> dict:
    """Per-object arrays for one batch (see `evaluate` for what they become). `pool`:
    Table 4's random tower shapes (`shape_pool`; drawn here from `key` when None).
    `table4`: simulate Table 4's sampling baselines too (with the baselines on): their
    candidates then follow the others in "hdist" and "mae" (`candidate_layout`); with
    `table4_every_batch` it must be."""
    if self.table4_fused and not table4:
      raise ValueError("this Evaluator simulates Table 4's baselines on every batch "
                       "(table4_every_batch=True): batch(table4=False) cannot skip them")
    if not self.compiled:
      self.compile(batch, key, pool)
    obs, true = self._inputs(batch)
    decoded = self._timed("decode", self._decode, self.state, obs, true, self.est_state)
    b, k = true.density.shape
    base_slots = (np.argmax(base_scores, -1).astype(np.int32) if base_scores is not None
                  else np.zeros((b, len(BASELINES), k), np.int32))
    keys = object_keys(key, b)
    table4 = table4 and self.baselines_on
    if table4 and pool is None:
      pool = shape_pool(key, self.samples, k)
    args = self._sample_args(decoded, true, base_slots, obs, keys, pool)
    pred, fitted, logits, fit_logits = args[:4]
    dist, mae, slots, fit_slots = self._timed("sample", self._simulate, *args)
    if table4 and not self.table4_fused:
      d4, m4 = self._timed("sample_table4", self._simulate_table4, true,
                           jax.tree.map(jnp.asarray, pool), obs["trajectories"], keys,
                           obs[PUSH_MAGNITUDES])
      dist, mae = jnp.concatenate([dist, d4], 1), jnp.concatenate([mae, m4], 1)
    out = jax.device_get({**decoded, "hdist": dist, "mae": mae, "slots": slots})
    out["dist"] = out["hdist"][..., SELECTION_HORIZONS.index(0)]  # the whole trajectory
    out["logp"] = np.asarray(_log_priors(logits, slots, pred.valid))
    out["fit_slots"] = {g: np.asarray(s) for g, s in zip(self.groups, fit_slots)}
    out["fit_logp"] = {g: np.asarray(_log_priors(fl, s, f.valid))
                       for g, s, f, fl in zip(self.groups, fit_slots, fitted, fit_logits)}
    if self.refine or self.joint:  # from the closest sample, on the most precise boxes
      group = self.refine_group
      prims, prior, d0, m0 = self._best_sample(out, decoded, group)
      if self.refine:
        out["refine"] = jax.device_get(self._timed("refine", self._refine, prims, prior,
                                                   obs["trajectories"], d0, m0,
                                                   obs[PUSH_MAGNITUDES]))
        out["refine"]["sample_dist"] = d0  # the start's distance
      if self.joint:
        depth = obs["depth"].astype(jnp.float32) if "depth" in obs else jnp.zeros((len(d0),))
        out["joint"] = jax.device_get(self._timed("joint", self._joint, prims, prior,
                                                  obs["trajectories"], depth, true,
                                                  obs[PUSH_MAGNITUDES]))
    if self.refine and "true" in self.groups:  # the oracle column refined alike
      prims, prior, d0, m0 = self._best_sample(out, decoded, "true")
      out["refine_true"] = jax.device_get(self._timed("refine", self._refine, prims, prior,
                                                      obs["trajectories"], d0, m0,
                                                      obs[PUSH_MAGNITUDES]))
    return out

  def _best_sample(self, out: dict, decoded: dict, group: str):
    """A group's candidate closest over the whole trajectory (for `decompose`'s group,
    among those its screen keeps, as `decompose` refines) as boxes with its densities,
    the group's logits (the MAP prior), and its distance and MAE."""
    fitted = group != "ppd"
    boxes = decoded["fitted"][group] if fitted else decoded["pred"]
    cand_slots = out["fit_slots"][group] if fitted else out["slots"]
    d, m = out["dist"][:, self.layout[group]], out["mae"][:, self.layout[group]]
    select = self.decompose.select
    keep = (screen_mask(out["hdist"][:, self.layout[group]], select.screen_steps,
                        select.screen_keep) if group == self.refine_group else True)
    best = np.argmin(np.where(keep, d, np.inf), -1)
    start = np.take_along_axis(cand_slots, best[:, None, None], 1)[:, 0]
    prims = boxes.replace(density=jnp.asarray(slot_to_density(start), jnp.float32))
    rows = np.arange(len(best))
    prior = decoded["group_logits"][group] if fitted else decoded["logits"]
    return prims, prior, d[rows, best], m[rows, best]

  def records(self, out: dict, slot, valid, base, *, prefixes, table4: bool = True,
              studies: bool = False, horizon_sweep: bool = False) -> dict:
    """One batch's per-object records (`rows.batch_records`) of `batch`'s output, with
    `decompose`'s settings for its row."""
    select = self.decompose.select
    return batch_records(out, slot, valid, base, samples=self.samples,
                         prior_weight=select.prior_weight,
                         network_prior_weight=select.tau(False), prefixes=prefixes,
                         with_baselines=self.baselines_on, refine=self.refine,
                         layout=self.layout, selection_horizon=select.horizon,
                         horizon_sweep=horizon_sweep, table4=table4, studies=studies,
                         headline=self.refine_group,
                         screen=(select.screen_steps, select.screen_keep))

  def headline_row(self) -> str:
    """The name of the Table 2 row that `decompose` with these settings returns."""
    return headline_row(self.decompose)
