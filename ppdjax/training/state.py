"""The train state (model and optimizer), its jitted steps, and the `Trainer` that holds it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset import storage
from ppdjax.nn import losses
from ppdjax.nn.model import PPD
from ppdjax.nn.resnet import load_torchvision_weights
from ppdjax.training import checkpoints, sharding
from ppdjax.training.loader import BATCH_KEYS, model_inputs


class TrainState(nnx.Module):
  """What training updates: the model and its optimizer, split and merged as one pytree
  (its State has the keys "model" and "optimizer", as the checkpoints do)."""

  def __init__(self, model: PPD, optimizer: nnx.Optimizer):
    self.model = model
    self.optimizer = optimizer


def build(config) -> TrainState:
  """A freshly initialised model (seeded by train.seed) and its Adam optimiser."""
  model = PPD(config.model, rngs=nnx.Rngs(params=config.train.seed))
  if config.model.image_weights:
    if not config.model.use_image:
      raise ValueError("config.model.image_weights is set but use_image is False")
    load_torchvision_weights(model.image_encoder, config.model.image_weights)
  tx = optax.adam(learning_rate(config.train), b1=0.9, b2=0.999)
  return TrainState(model, nnx.Optimizer(model, tx, wrt=nnx.Param))


def learning_rate(t):
  """Adam's rate: constant (the paper's), or cosine-decayed to 0 over all the run's steps.

  The geometry loss is an L1: its gradients keep their size near the optimum, so at a
  constant rate the boxes jitter at the rate's scale; the decay lets them settle
  (docs/training.md).
  """
  if t.get("schedule", "constant") == "constant":
    return t.learning_rate
  if t.schedule != "cosine":
    raise ValueError(f"config.train.schedule must be 'constant' or 'cosine', got {t.schedule!r}")
  return optax.cosine_decay_schedule(t.learning_rate, t.geometry_steps + t.joint_steps)


def _loss(model, batch, w, train, key):
  rngs = nnx.Rngs(dropout=key) if key is not None else None
  tgt = losses.targets(batch["primitives"])
  pred = model(batch, tgt["prev"], train=train, rngs=rngs)
  return losses.loss_fn(pred, tgt, w)


def train_step(graphdef, state, batch, step, w, seed):
  """One Adam step; pure in (state, batch, step): the dropout key is fold_in(seed, step)."""
  ts = nnx.merge(graphdef, state)
  key = jax.random.fold_in(jax.random.key(seed), step)
  grads, aux = nnx.grad(lambda m: _loss(m, batch, w, True, key), has_aux=True)(ts.model)
  ts.optimizer.update(ts.model, grads)
  return nnx.state(ts), aux


def eval_step(graphdef, state, batch, w):
  """Validation loss (teacher forced, eval mode) and metric counts of decoded predictions."""
  model = nnx.merge(graphdef, state).model
  tgt = losses.targets(batch["primitives"])
  _, aux = losses.loss_fn(model(batch, tgt["prev"], train=False), tgt, w)
  pred, raw = model.decode(batch)
  k = pred.num_slots  # density: k-th step vs k-th true box (bottom to top); F1 is order-free
  counts = metrics.density_counts(raw.density_logits[:, :k, :NUM_DENSITY_SLOTS],
                                  tgt["slot"], tgt["geometry_mask"][:, :k])
  counts.update(metrics.shape_counts(pred, batch["primitives"]))
  return aux, jax.tree.map(jnp.sum, counts)


class Trainer:
  """Holds the replicated train state, compiles the steps once and checkpoints them."""

  def __init__(self, config, workdir: str):
    self.config, self.workdir = config, workdir
    self.mesh = sharding.make_mesh()
    self.replicated = sharding.replicated(self.mesh)
    self.graphdef, state = nnx.split(build(config))
    self.state = jax.device_put(state, self.replicated)
    self.latest, self.best = checkpoints.managers(workdir, config.train.keep_checkpoints)
    seed = config.train.seed
    self._train = jax.jit(lambda s, b, i, w: train_step(self.graphdef, s, b, i, w, seed),
                          out_shardings=(self.replicated, self.replicated), donate_argnums=0)
    self._eval = jax.jit(lambda s, b, w: eval_step(self.graphdef, s, b, w),
                         out_shardings=self.replicated)

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
    return 0

  def train_step(self, batch, step: int, w: float) -> dict:
    self.state, aux = self._train(self.state, batch, jnp.int32(step), jnp.float32(w))
    return aux

  def evaluate(self, dataset: storage.Dataset, num_batches: int) -> dict:
    """Validation loss and metrics (density top-1/5/10 %, RMSE in slots, shape F1 %)."""
    devices = jax.device_count()
    bs = min(self.config.train.batch_size, len(dataset) // devices * devices)
    if bs == 0:
      raise ValueError(f"the validation split has {len(dataset)} samples, fewer than the "
                       f"{devices} devices")
    sums, aux_sum, n = None, None, 0
    batches = storage.batches(dataset, bs, seed=0, part=(jax.process_index(), jax.process_count()),
                           keys=BATCH_KEYS)
    for i, batch in enumerate(batches):
      if num_batches and i >= num_batches:
        break
      batch = sharding.global_batch(model_inputs(batch), sharding.batch_sharded(self.mesh))
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
