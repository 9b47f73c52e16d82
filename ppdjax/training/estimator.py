"""Training the density estimator on simulated towers, and saving and loading it.

`train_estimator(config, workdir)` simulates a training and a validation pool of fresh
towers with densities (`dataset.physics_stream`; no rendering, no dataset on disk), then
fits `nn.estimator.DensityEstimator` to them with AdamW: cross-entropy against a Gaussian
about the true slot, on boxes whose faces are jittered by `box_noise` metres (the fitted
boxes it will read at test time are that far off). Every `eval_every` steps it logs the
validation top-1 / RMSE to `metrics.jsonl` and saves `resume.npz`; a run stopped by
`max_seconds` (or killed) resumes there. At the end the weights go to `estimator.npz`
beside `estimator.json` (the config section and the file's sha256): what `load` reads.
"""

from __future__ import annotations

import hashlib
import json
import os
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import nnx
from tqdm.auto import tqdm

from ppdjax.dataset.physics_stream import simulate_pool
from ppdjax.dataset.readers import read_json, read_npz
from ppdjax.nn.estimator import DensityEstimator, slot_targets
from ppdjax.training.checkpoints import CheckpointError

CONFIG, WEIGHTS, RESUME, METRICS = "estimator.json", "estimator.npz", "resume.npz", "metrics.jsonl"
VAL_SEED_OFFSET = 1_000_003  # the validation pool's seed: seed + this


def check_config(e) -> None:
  """Raises ValueError naming the first bad value of an `estimator` section."""
  rules = [("pool_size", e.pool_size >= 1), ("val_size", e.val_size >= 1),
           ("steps", e.steps >= 1), ("batch_size", 1 <= e.batch_size),
           ("learning_rate", e.learning_rate > 0), ("warmup_steps", 0 <= e.warmup_steps < e.steps),
           ("label_sigma", e.label_sigma >= 0), ("box_noise", 0 <= e.box_noise < 0.05),
           ("channels", len(e.channels) >= 1 and min(e.channels) >= 1),
           ("hidden", e.hidden >= 1), ("layers", e.layers >= 1), ("steps_in", e.steps_in >= 1),
           ("eval_every", e.eval_every >= 1)]
  for key, ok in rules:
    if not ok:
      raise ValueError(f"config.estimator.{key} has a bad value: {e[key]!r}")


def noisy_boxes(key: jax.Array, prims, sigma: float):
  """Boxes with each centre and half size moved by N(0, sigma) metres (padding untouched)."""
  kp, kh = jax.random.split(key)
  keep = prims.valid[..., None]
  pos = prims.pos + sigma * jax.random.normal(kp, prims.pos.shape)
  half = jnp.maximum(prims.half_size + sigma * jax.random.normal(kh, prims.half_size.shape),
                     1e-3)
  return prims.replace(pos=jnp.where(keep, pos, prims.pos),
                       half_size=jnp.where(keep, half, prims.half_size))


def loss_fn(model, prims, traj, slots, sigma):
  """Mean cross-entropy over real boxes, against `slot_targets(slots, sigma)`."""
  logits = model(prims, traj)
  ce = -jnp.sum(slot_targets(slots, sigma) * jax.nn.log_softmax(logits, -1), -1)
  return jnp.sum(jnp.where(prims.valid, ce, 0.0)) / jnp.maximum(prims.valid.sum(), 1)


def density_metrics(logits, slots, valid) -> dict:
  """Arg-max top-1 (%), top-5 (%) and RMSE (slots) over real boxes."""
  own = jnp.take_along_axis(logits, slots[..., None], -1)
  rank = jnp.sum(logits > own, -1)
  err = jnp.argmax(logits, -1) - slots
  n = jnp.maximum(valid.sum(), 1)
  return {"top1": 100.0 * jnp.sum(valid & (rank < 1)) / n,
          "top5": 100.0 * jnp.sum(valid & (rank < 5)) / n,
          "rmse": jnp.sqrt(jnp.sum(jnp.where(valid, err * err, 0)) / n)}


def build(e):
  """A fresh estimator and its optimiser (AdamW, warm-up then cosine, clipped)."""
  model = DensityEstimator(e, rngs=nnx.Rngs(params=e.seed))
  rate = optax.warmup_cosine_decay_schedule(0.0, e.learning_rate, max(e.warmup_steps, 1),
                                            e.steps)
  tx = optax.chain(optax.clip_by_global_norm(e.clip_norm),
                   optax.adamw(rate, weight_decay=e.weight_decay))
  return model, nnx.Optimizer(model, tx, wrt=nnx.Param)


def _leaves(*modules):
  return [np.asarray(x) for x in jax.tree.leaves(nnx.state(modules))]


def _restore(modules, leaves):
  state = nnx.state(modules)
  nnx.update(modules, jax.tree.unflatten(jax.tree.structure(state),
                                         [jnp.asarray(x) for x in leaves]))


def _config_text(e) -> str:
  return ml_collections.ConfigDict(e.to_dict()).to_json_best_effort(sort_keys=True, indent=1)


def train_estimator(config, workdir: str, *, max_seconds: float = 0.0,
                    progress: bool = True) -> dict:
  """Trains (or resumes) the estimator of `config.estimator` in `workdir`.

  Args:
    config: a preset with an `estimator` section.
    workdir: where estimator.json, metrics.jsonl, resume.npz and estimator.npz go.
    max_seconds: > 0 stops (after saving) once this much time has passed; call again to go on.
    progress: progress bars.

  Returns:
    {"step", "done", and the last validation metrics}.
  """
  e = config.estimator
  check_config(e)
  os.makedirs(workdir, exist_ok=True)
  text = _config_text(e)
  cfg_path = os.path.join(workdir, CONFIG)
  if os.path.exists(os.path.join(workdir, RESUME)) and os.path.exists(cfg_path):
    with open(cfg_path) as f:
      if json.load(f).get("config") != json.loads(text):
        raise ValueError(f"{workdir} holds an estimator run with another config; use a new "
                         "workdir")
  t0 = time.perf_counter()
  pool = simulate_pool(e.seed, e.pool_size, steps=e.steps_in, progress=progress,
                       desc="training pool")
  val = simulate_pool(e.seed + VAL_SEED_OFFSET, e.val_size, steps=e.steps_in,
                      progress=progress, desc="validation pool")
  model, opt = build(e)
  graphdef, state = nnx.split((model, opt))
  start = 0
  resume_path = os.path.join(workdir, RESUME)
  if os.path.exists(resume_path):
    with np.load(resume_path) as z:
      start = int(z["step"])
      _restore((model, opt), [z[f"leaf_{i:04d}"] for i in range(len(z.files) - 1)])
    graphdef, state = nnx.split((model, opt))
  else:
    with open(cfg_path, "w") as f:
      json.dump({"config": json.loads(text)}, f, indent=1)

  @jax.jit
  def train_step(state, step, pool):  # the pool is an argument: a closure would be a constant
    model, opt = nnx.merge(graphdef, state)
    key = jax.random.fold_in(jax.random.key(e.seed), step)
    ki, kn = jax.random.split(key)
    idx = jax.random.randint(ki, (e.batch_size,), 0, e.pool_size)
    prims = noisy_boxes(kn, jax.tree.map(lambda x: x[idx], pool["primitives"]), e.box_noise)
    loss, grads = nnx.value_and_grad(loss_fn)(model, prims, pool["trajectories"][idx],
                                              pool["slots"][idx], e.label_sigma)
    opt.update(model, grads)
    return nnx.state((model, opt)), loss

  @jax.jit
  def val_logits(state, prims, traj):
    model, _ = nnx.merge(graphdef, state)
    return model(prims, traj)

  def validate(state) -> dict:
    prims = noisy_boxes(jax.random.key(e.seed + 1), val["primitives"], e.box_noise)
    logits = jnp.concatenate([
        val_logits(state, jax.tree.map(lambda x: x[i:i + 1024], prims),
                   val["trajectories"][i:i + 1024]) for i in range(0, e.val_size, 1024)])
    return {k: float(v) for k, v in density_metrics(logits, val["slots"], prims.valid).items()}

  log = open(os.path.join(workdir, METRICS), "a")
  last, losses, step = {}, [], start
  bar = tqdm(total=e.steps, initial=start, desc="estimator", unit="step", disable=not progress)
  try:
    for step in range(start, e.steps):
      state, loss = train_step(state, step, pool)
      losses.append(loss)
      bar.update(1)
      at_end = step + 1 == e.steps
      timed_out = max_seconds > 0 and time.perf_counter() - t0 > max_seconds
      if (step + 1) % e.eval_every == 0 or at_end or timed_out:
        last = {"step": step + 1, "loss": float(jnp.mean(jnp.stack(losses))),
                **{f"val_{k}": v for k, v in validate(state).items()},
                "seconds": round(time.perf_counter() - t0, 1)}
        losses = []
        log.write(json.dumps(last) + "\n")
        log.flush()
        bar.set_postfix(top1=f"{last['val_top1']:.1f}", rmse=f"{last['val_rmse']:.2f}")
        nnx.update((model, opt), state)
        leaves = _leaves(model, opt)
        np.savez(resume_path + ".tmp.npz", step=step + 1,
                 **{f"leaf_{i:04d}": x for i, x in enumerate(leaves)})
        os.replace(resume_path + ".tmp.npz", resume_path)
        if timed_out and not at_end:
          return {**last, "done": False}
  finally:
    bar.close()
    log.close()
  nnx.update((model, opt), state)
  save(model, e, workdir)
  return {**last, "step": e.steps, "done": True}


def save(model: DensityEstimator, e, folder: str, dtype: str = "float16") -> dict:
  """Writes the estimator's weights (estimator.npz, floats as `dtype`) and estimator.json."""
  os.makedirs(folder, exist_ok=True)
  pure = nnx.to_pure_dict(nnx.state(model, nnx.Param))
  flat = {"/".join(map(str, k)): np.asarray(v).astype(dtype)
          for k, v in _flatten(pure).items()}
  path = os.path.join(folder, WEIGHTS)
  np.savez(path, **flat)
  with open(path, "rb") as f:
    digest = hashlib.sha256(f.read()).hexdigest()
  record = {"config": json.loads(_config_text(e)), "weights": WEIGHTS, "sha256": digest,
            "dtype": dtype, "parameters": int(sum(v.size for v in flat.values()))}
  with open(os.path.join(folder, CONFIG), "w") as f:
    json.dump(record, f, indent=1)
  return record


def _flatten(d, prefix=()):
  out = {}
  for k, v in d.items():
    out.update(_flatten(v, prefix + (k,)) if isinstance(v, dict) else {prefix + (k,): v})
  return out


def load(folder: str) -> tuple[DensityEstimator, ml_collections.ConfigDict]:
  """(estimator, its config section) from a folder `save` or `train_estimator` wrote.

  Raises:
    CheckpointError for a missing, incomplete or corrupt folder.
  """
  cfg_path, path = os.path.join(folder, CONFIG), os.path.join(folder, WEIGHTS)
  if not os.path.exists(cfg_path):
    raise CheckpointError(f"{folder} holds no trained density estimator ({CONFIG} and "
                          f"{WEIGHTS}); train one with python -m ppdjax.train_estimator")
  record = read_json(cfg_path, error=CheckpointError, missing=CheckpointError)
  if not isinstance(record.get("config"), dict):
    raise CheckpointError(f"{cfg_path} is corrupt: it lacks the estimator's 'config'")
  if "sha256" not in record or not os.path.exists(path):
    raise CheckpointError(f"{folder}: {WEIGHTS} is missing (the run did not finish; run "
                          "python -m ppdjax.train_estimator again to resume)")
  with open(path, "rb") as f:
    if hashlib.sha256(f.read()).hexdigest() != record["sha256"]:
      raise CheckpointError(f"{path} is corrupt (sha256 differs from {CONFIG})")
  e = ml_collections.ConfigDict(record["config"])
  e.channels = tuple(e.channels)
  model = DensityEstimator(e, rngs=nnx.Rngs(params=0))
  state = nnx.state(model, nnx.Param)
  pure = nnx.to_pure_dict(state)
  arrays = read_npz(path, "density estimator weights", error=CheckpointError,
                    missing=CheckpointError)
  flat = _flatten(pure)
  missing = ["/".join(map(str, k)) for k in flat if "/".join(map(str, k)) not in arrays]
  if missing:
    raise CheckpointError(f"{path} lacks weights for {missing[:3]}")
  differ = [k for k in flat if arrays["/".join(map(str, k))].shape != tuple(flat[k].shape)]
  if differ:
    k = "/".join(map(str, differ[0]))
    raise CheckpointError(f"{path} does not match {cfg_path}: {k} is "
                          f"{arrays[k].shape} in the weights, {tuple(flat[differ[0]].shape)} "
                          "in the model the config describes")

  def fill(tree, prefix=()):
    return {k: fill(v, prefix + (k,)) if isinstance(v, dict)
            else jnp.asarray(arrays["/".join(map(str, prefix + (k,)))], jnp.float32)
            for k, v in tree.items()}
  nnx.replace_by_pure_dict(state, fill(pure))
  nnx.update(model, state)
  return model, e
