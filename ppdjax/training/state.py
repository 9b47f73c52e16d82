"""The train state (model and optimizer), its jitted steps, and the `Trainer` that holds it."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset import batching, depth_video, storage, stream
from ppdjax.nn import losses
from ppdjax.nn.model import PPD, init_ppd
from ppdjax.nn.resnet import load_torchvision_weights
from ppdjax.training import checkpoints, sharding, streams
from ppdjax.training.loader import BATCH_KEYS, model_inputs

BATCH_NORM_MODES = ("global", "per_device")  # train.batch_norm: see Trainer


def batch_norm_mode(t) -> str:
  """`train.batch_norm` ("global" where a saved run predates it); ValueError if unknown."""
  mode = t.get("batch_norm", "global")
  if mode not in BATCH_NORM_MODES:
    raise ValueError(f"config.train.batch_norm must be one of {BATCH_NORM_MODES}, got "
                     f"{mode!r}")
  return mode


class TrainState(nnx.Module):
  """What training updates: the model and its optimizer, split and merged as one pytree
  (its State has the keys "model" and "optimizer", as the checkpoints do)."""

  def __init__(self, model: PPD, optimizer: nnx.Optimizer):
    self.model = model
    self.optimizer = optimizer


def build(config) -> TrainState:
  """A freshly initialised model (seeded by train.seed) and its Adam optimiser."""
  model = init_ppd(config.model, config.train.seed)
  if config.model.image_weights:
    if not config.model.use_image:
      raise ValueError("config.model.image_weights is set but use_image is False")
    load_torchvision_weights(model.image_encoder, config.model.image_weights)
  tx = optax.adam(learning_rate(config.train), b1=0.9, b2=0.999)
  if config.train.get("clip_norm", 0.0) > 0:  # gradients rescaled to this global norm first
    tx = optax.chain(optax.clip_by_global_norm(config.train.clip_norm), tx)
  return TrainState(model, nnx.Optimizer(model, tx, wrt=nnx.Param))


def learning_rate(t):
  """Adam's rate: constant (the paper's), or cosine-decayed to 0 over all the run's steps.

  The geometry loss is an L1: its gradients keep their size near the optimum, so at a
  constant rate the boxes jitter at the rate's scale; the decay lets them settle
  (docs/training.md). With `warmup_steps` > 0 the rate first rises linearly from 0 over those steps.
  """
  warmup = t.get("warmup_steps", 0)
  if warmup and warmup >= total_steps(t):
    raise ValueError(f"config.train.warmup_steps ({warmup}) must be below the run's "
                     f"{total_steps(t)} steps")
  if t.get("schedule", "constant") == "constant":
    if not warmup:
      return t.learning_rate
    return optax.join_schedules([optax.linear_schedule(0.0, t.learning_rate, warmup),
                                 optax.constant_schedule(t.learning_rate)], [warmup])
  if t.schedule != "cosine":
    raise ValueError(f"config.train.schedule must be 'constant' or 'cosine', got {t.schedule!r}")
  if warmup:
    return optax.warmup_cosine_decay_schedule(0.0, t.learning_rate, warmup, total_steps(t))
  return optax.cosine_decay_schedule(t.learning_rate, total_steps(t))


def total_steps(t) -> int:
  """All of a run's steps: geometry stream, geometry phase, joint phase."""
  return t.get("stream_steps", 0) + t.geometry_steps + t.joint_steps


def phase(t, step: int) -> int:
  """0: the geometry stream (voxels of fresh towers), 1: geometry on the dataset (w = 0),
  2: joint (w > 0)."""
  s = t.get("stream_steps", 0)
  return 0 if step < s else 1 if step < s + t.geometry_steps else 2


def density_weight(t, step: int) -> float:
  """w of Eq. 4-5 at `step`: 0 before the joint phase; in it `density_weight`, reached
  linearly over its first `density_ramp_steps` steps (0: at once, as the paper).

  A ramp softens the joint phase's start, where the density head, idle through the
  geometry phase, brings a loss of tens of nats while Adam's moments hold only geometry's
  gradients (on the tools, validation F1 fell from 68 to 21 in 50 steps; docs/data.md).
  """
  if phase(t, step) != 2:
    return 0.0
  ramp = t.get("density_ramp_steps", 0)
  into = step - t.get("stream_steps", 0) - t.geometry_steps + 1  # 1 at the phase's first step
  return float(t.density_weight) * (min(1.0, into / ramp) if ramp > 0 else 1.0)


def loss_weights(t) -> dict:
  """The loss terms' weights from a preset's `train` section (see `losses.loss_fn`).

  A run saved before `end_weight` existed weighted the end token with w, as the paper.
  """
  return {"end_weight": t.get("end_weight", None), "geometry_weight": t.get("geometry_weight", 1.0)}


def _loss(model, batch, w, train, key, weights):
  rngs = nnx.Rngs(dropout=key) if key is not None else None
  tgt = losses.targets(batch["primitives"])
  batch = depth_video.with_depth_video(batch, model.video)  # the RGB-D row's, on the device
  pred = model(batch, tgt["prev"], train=train, rngs=rngs)
  end = w if weights["end_weight"] is None else weights["end_weight"]
  return losses.loss_fn(pred, tgt, w, end_weight=end,
                        geometry_weight=weights["geometry_weight"])


def train_step(graphdef, state, batch, step, w, t, sharding=None, axis=None, devices=1,
               physics=None):
  """One Adam step; pure in (state, batch, step): the dropout key is fold_in(seed, step).

  `batch` None is a step of the geometry stream alone (voxels of fresh towers, w = 0);
  otherwise, with `train.stream_weight` > 0, a stream batch's geometry and end-token
  loss joins the dataset's, so the voxel pathway keeps seeing unlimited geometries; and
  with `physics` (`streams.physics_batch_fn`), a physics-stream batch's whole loss,
  weighted by `train.physics_stream_weight`.

  `axis` names the mesh axis when each of `devices` devices runs this on its share of the
  batch (`jax.shard_map`; `train.batch_norm = "per_device"`): BatchNorm then normalises
  by the device's own statistics, and the gradients, batch statistics and logged losses
  are averaged over the devices once, at the end (`Trainer`).
  """
  ts = nnx.merge(graphdef, state)
  key = jax.random.fold_in(jax.random.key(t.seed), step)
  if axis is not None:  # each device its own dropout masks
    key = jax.random.fold_in(key, jax.lax.axis_index(axis))
  weights, stream_weight = loss_weights(t), t.get("stream_weight", 0.0)
  streamed = lambda: streams.geometry_batch(t, step, sharding, axis, devices)

  def total(m):
    if batch is None:
      return _loss(m, streamed(), 0.0, True, key, weights)
    loss, aux = _loss(m, batch, w, True, key, weights)
    if stream_weight > 0:
      s_loss, s_aux = _loss(m, streamed(), 0.0, True, jax.random.fold_in(key, 1), weights)
      loss = loss + stream_weight * s_loss
      aux = {**aux, "loss": loss, "stream_geometry_loss": s_aux["geometry_loss"]}
    if physics is not None:
      p_loss, p_aux = _loss(m, physics(t, step, sharding, axis, devices), w, True,
                            jax.random.fold_in(key, 2), weights)
      loss = loss + t.physics_stream_weight * p_loss
      aux = {**aux, "loss": loss, "physics_density_loss": p_aux["density_loss"]}
    return loss, aux

  grads, aux = nnx.grad(total, has_aux=True)(ts.model)
  if axis is not None:
    grads, aux = jax.lax.pmean((grads, aux), axis)
    nnx.update(ts.model, jax.lax.pmean(nnx.state(ts.model, nnx.BatchStat), axis))
  ts.optimizer.update(ts.model, grads)
  if batch is None:
    aux = {k: v for k, v in aux.items() if k != "density_loss"}  # placeholder densities
  return nnx.state(ts), aux


def eval_step(graphdef, state, batch, w, weights):
  """Validation loss (teacher forced, eval mode) and metric counts of decoded predictions."""
  model = nnx.merge(graphdef, state).model
  tgt, batch = losses.targets(batch["primitives"]), depth_video.with_depth_video(batch, model.video)
  end = w if weights["end_weight"] is None else weights["end_weight"]
  _, aux = losses.loss_fn(model(batch, tgt["prev"], train=False), tgt, w, end_weight=end,
                          geometry_weight=weights["geometry_weight"])
  pred, raw = model.decode(batch)
  k = pred.num_slots  # density: k-th step vs k-th true box (bottom to top); F1 is order-free
  counts = metrics.density_counts(raw.density_logits[:, :k, :NUM_DENSITY_SLOTS],
                                  tgt["slot"], tgt["geometry_mask"][:, :k])
  counts.update(metrics.shape_counts(pred, batch["primitives"]))
  return aux, jax.tree.map(jnp.sum, counts)


def init_from(model: PPD, workdir: str) -> list[str]:
  """Copies into `model` every parameter and batch statistic of another run's latest model
  whose path and shape match (the voxel encoder and generator of a geometry-stage run,
  say); returns the paths copied. Warns, naming them, about arrays both models have at
  another shape (those start fresh). Raises ValueError if nothing matches."""
  source, _ = checkpoints.load(workdir, which="latest")
  src = _flat(nnx.to_pure_dict(nnx.state(source)))
  dst = nnx.to_pure_dict(nnx.state(model))
  both = {p: v for p, v in _flat(dst).items() if p in src}
  copied = [p for p, v in both.items() if np.shape(src[p]) == np.shape(v)]
  if not copied:
    raise ValueError(f"train.init_from={workdir}: no parameter matches this model")
  reshaped = [f"{'/'.join(map(str, p))} {np.shape(src[p])} -> {np.shape(v)}"
              for p, v in both.items() if np.shape(src[p]) != np.shape(v)]
  if reshaped:
    warnings.warn(f"train.init_from={workdir}: {len(reshaped)} arrays have another shape "
                  "here and start fresh: " + "; ".join(reshaped), stacklevel=2)
  _assign(dst, {p: src[p] for p in copied})
  state = nnx.state(model)
  nnx.replace_by_pure_dict(state, dst)
  nnx.update(model, state)
  return ["/".join(map(str, p)) for p in copied]


def _flat(d, prefix=()):
  out = {}
  for k, v in d.items():
    out.update(_flat(v, prefix + (k,)) if isinstance(v, dict) else {prefix + (k,): v})
  return out


def _assign(d, values):
  for path, v in values.items():
    node = d
    for k in path[:-1]:
      node = node[k]
    node[path[-1]] = jnp.asarray(v)


class Trainer:
  """Holds the replicated train state, compiles the steps once and checkpoints them."""

  def __init__(self, config, workdir: str, devices=None):
    """`devices`: the devices the batch splits over (None: every device of every process)."""
    self.config, self.workdir = config, workdir
    self.mesh = sharding.make_mesh(devices)
    self.replicated = sharding.replicated(self.mesh)
    self.graphdef, state = nnx.split(build(config))
    self.state = jax.device_put(state, self.replicated)
    self.latest, self.best = checkpoints.managers(workdir, config.train.keep_checkpoints)
    t, batch_sharding = config.train, sharding.batch_sharded(self.mesh)
    self._train = self._compile_train_step(t, batch_sharding)
    weights = loss_weights(t)
    self._eval = jax.jit(lambda s, b, w: eval_step(self.graphdef, s, b, w, weights),
                         out_shardings=self.replicated)

  def _compile_train_step(self, t, batch_sharding):
    """The jitted step. Over several devices BatchNorm takes its statistics either over
    the whole batch (`train.batch_norm = "global"`: the partitioner all-reduces them at
    every normalisation, forward and backward; the math of one device) or over each
    device's share (`"per_device"`: a `jax.shard_map` step whose only collective is the
    average of gradients, statistics and losses at its end)."""
    physics = (streams.physics_batch_fn(self.config.data)
               if t.get("physics_stream_weight", 0.0) > 0 else None)
    if batch_norm_mode(t) == "global" or self.mesh.size == 1:
      return jax.jit(lambda s, b, i, w: train_step(self.graphdef, s, b, i, w, t,
                                                   batch_sharding, physics=physics),
                     out_shardings=(self.replicated, self.replicated), donate_argnums=0)
    P, n = jax.sharding.PartitionSpec, self.mesh.size
    local = jax.shard_map(
        lambda s, b, i, w: train_step(self.graphdef, s, b, i, w, t, None,
                                      sharding.DATA_AXIS, n, physics),
        mesh=self.mesh, in_specs=(P(), P(sharding.DATA_AXIS), P(), P()),
        out_specs=(P(), P()), check_vma=False)
    return jax.jit(local, donate_argnums=0)

  def restore_latest(self) -> int:
    """Restores the newest intact checkpoint if there is one; returns its step (0 if none).

    A checkpoint that cannot be read (a truncated file after a crash, say) is reported
    and the next older one is tried; CheckpointError if none of them can be read.
    """
    steps = sorted(self.latest.all_steps(), reverse=True)
    for n, step in enumerate(steps):
      try:
        got = checkpoints.restore(self.latest, step, model=self.state["model"],
                                  optimizer=self.state["optimizer"])
      except checkpoints.CheckpointError as e:
        older = f"trying step {steps[n + 1]}" if n + 1 < len(steps) else "none older"
        print(f"warning: {e}; {older}", flush=True)
        continue
      self.state = jax.device_put(nnx.State({"model": got["model"],
                                             "optimizer": got["optimizer"]}), self.replicated)
      if n:
        moved = checkpoints.set_aside(self.latest, steps[:n], self.workdir)
        print(f"resuming from step {step}, the newest intact checkpoint (unreadable steps "
              f"{steps[:n]} moved to {moved})", flush=True)
      return int(step)
    if steps:
      raise checkpoints.CheckpointError(
          f"no checkpoint in {self.latest.directory} can be read (steps {steps}); move the "
          "folder away to start again")
    if self.config.train.get("init_from", ""):
      ts = nnx.merge(self.graphdef, self.state)
      copied = init_from(ts.model, self.config.train.init_from)
      self.state = jax.device_put(nnx.state(ts), self.replicated)
      print(f"initialised {len(copied)} arrays from {self.config.train.init_from}", flush=True)
    return 0

  def train_step(self, batch, step: int, w: float) -> dict:
    """One step on `batch` (None: a geometry-stream step)."""
    self.state, aux = self._train(self.state, batch, jnp.int32(step), jnp.float32(w))
    return aux

  def evaluate(self, dataset: storage.Dataset | None, num_batches: int) -> dict:
    """Validation loss and metrics (density top-1/5/10 %, RMSE in slots, shape F1 %).

    `dataset` None (a geometry-stage run, which reads no dataset): `num_batches` batches
    of fresh towers from a held-out stream (voxels only; geometry and F1 are what count).
    """
    devices, t = self.mesh.size, self.config.train
    if dataset is None:
      if not num_batches:
        raise ValueError("validation on the stream needs train.eval_batches > 0")
      key = jax.random.key(t.seed + streams.VAL_STREAM_SEED)
      batches = (jax.device_get(stream.geometry_batch(jax.random.fold_in(key, i),
                                                      t.batch_size, False))
                 for i in range(num_batches))
    else:
      bs = min(t.batch_size, len(dataset) // devices * devices)
      if bs == 0:
        raise ValueError(f"the validation split has {len(dataset)} samples, fewer than the "
                         f"{devices} devices")
      batches = (model_inputs(b) for b in batching.batches(
          dataset, bs, seed=0, part=(jax.process_index(), jax.process_count()),
          keys=BATCH_KEYS))
    sums, aux_sum, n = None, None, 0
    for i, batch in enumerate(batches):
      if num_batches and i >= num_batches:
        break
      batch = sharding.global_batch(batch, sharding.batch_sharded(self.mesh))
      aux, counts = jax.device_get(self._eval(self.state, batch,
                                              jnp.float32(self.config.train.density_weight)))
      sums = counts if sums is None else jax.tree.map(np.add, sums, counts)
      aux_sum = aux if aux_sum is None else jax.tree.map(np.add, aux_sum, aux)
      n += 1
    out = {k: float(v) / n for k, v in aux_sum.items()}
    out.update({("density_" + k if k != "f1" else "shape_f1"): v
                for k, v in metrics.summarize(sums).items()})
    return out

  def save(self, step: int, val_loss: float | None) -> None:
    checkpoints.save(self.latest, self.best, step, self.state["model"],
                     self.state["optimizer"], val_loss)

  def close(self) -> None:
    self.latest.wait_until_finished()
    self.best.wait_until_finished()
    self.latest.close()
    self.best.close()
