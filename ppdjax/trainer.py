"""The train state and its jitted steps: one split (model, optimizer) pytree on a device mesh."""

from __future__ import annotations

import queue
import threading

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from ppdjax import checkpoints, data, losses, metrics, sharding
from ppdjax.materials import NUM_DENSITY_SLOTS
from ppdjax.model import PPD
from ppdjax.resnet import load_torchvision_weights

OBS_KEYS = ("voxels", "image", "trajectories")
BATCH_KEYS = OBS_KEYS + ("primitives",)  # what training reads from disk


def model_inputs(batch: dict) -> dict:
  """The arrays a step needs from a loader batch (observations and ground truth)."""
  return {**{k: batch[k] for k in OBS_KEYS}, "primitives": batch["primitives"]}


def build(config) -> tuple[PPD, nnx.Optimizer]:
  """A freshly initialised model (seeded by train.seed) and its Adam optimiser."""
  model = PPD(config.model, rngs=nnx.Rngs(params=config.train.seed))
  if config.model.image_weights:
    if not config.model.use_image:
      raise ValueError("config.model.image_weights is set but use_image is False")
    load_torchvision_weights(model.image_encoder, config.model.image_weights)
  tx = optax.adam(learning_rate(config.train), b1=0.9, b2=0.999)
  return model, nnx.Optimizer(model, tx, wrt=nnx.Param)


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
  model, optimizer = nnx.merge(graphdef, state)
  key = jax.random.fold_in(jax.random.key(seed), step)
  grads, aux = nnx.grad(lambda m: _loss(m, batch, w, True, key), has_aux=True)(model)
  optimizer.update(model, grads)
  return nnx.state((model, optimizer)), aux


def eval_step(graphdef, state, batch, w):
  """Validation loss (teacher forced, eval mode) and metric counts of decoded predictions."""
  model, _ = nnx.merge(graphdef, state)
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
    """Restores the newest checkpoint if there is one; returns its step (0 if none)."""
    step = self.latest.latest_step()
    if step is None:
      return 0
    got = checkpoints.restore(self.latest, step, model=self.state[0], optimizer=self.state[1])
    self.state = jax.device_put(nnx.State({0: got["model"], 1: got["optimizer"]}),
                                self.replicated)
    return int(step)

  def train_step(self, batch, step: int, w: float) -> dict:
    self.state, aux = self._train(self.state, batch, jnp.int32(step), jnp.float32(w))
    return aux

  def evaluate(self, dataset: data.Dataset, num_batches: int) -> dict:
    """Validation loss and metrics (density top-1/5/10 %, RMSE in slots, shape F1 %)."""
    devices = jax.device_count()
    bs = min(self.config.train.batch_size, len(dataset) // devices * devices)
    if bs == 0:
      raise ValueError(f"the validation split has {len(dataset)} samples, fewer than the "
                       f"{devices} devices")
    sums, n = None, 0
    batches = data.batches(dataset, bs, seed=0, part=(jax.process_index(), jax.process_count()),
                           keys=BATCH_KEYS)
    for i, batch in enumerate(batches):
      if num_batches and i >= num_batches:
        break
      batch = sharding.global_batch(model_inputs(batch), sharding.batch_sharded(self.mesh))
      aux, counts = jax.device_get(self._eval(self.state, batch,
                                              jnp.float32(self.config.train.density_weight)))
      sums = counts if sums is None else jax.tree.map(np.add, sums, counts)
      aux_sum = aux if n == 0 else jax.tree.map(np.add, aux_sum, aux)
      n += 1
    out = {k: float(v) / n for k, v in aux_sum.items()}
    out.update({("density_" + k if k != "f1" else "shape_f1"): v
                for k, v in metrics.summarize(sums).items()})
    return out

  def save(self, step: int, val_loss: float | None) -> None:
    checkpoints.save(self.latest, self.best, step, self.state[0], self.state[1], val_loss)

  def close(self) -> None:
    self.latest.wait_until_finished()
    self.best.wait_until_finished()
    self.latest.close()
    self.best.close()


class Loader:
  """Training batches for steps start_step, start_step + 1, ... read ahead in a thread.

  Step s reads batch s mod E of epoch s // E (E full batches per epoch), each epoch
  shuffled by (seed, epoch): the data position is a function of the step, so a resumed
  run sees exactly the batches an uninterrupted one would.
  """

  def __init__(self, dataset, batch_size: int, *, seed: int, start_step: int, prefetch: int,
               mesh):
    self.dataset, self.batch_size, self.seed = dataset, batch_size, seed
    self.part = (jax.process_index(), jax.process_count())
    self.sharding = sharding.batch_sharded(mesh)
    self.per_epoch = len(dataset) // batch_size
    self._queue = queue.Queue(maxsize=max(prefetch, 1))
    self._stop = threading.Event()
    self._thread = threading.Thread(target=self._fill, args=(start_step,), daemon=True)
    self._thread.start()

  def _fill(self, step):
    try:
      while not self._stop.is_set():
        epoch, index = divmod(step, self.per_epoch)
        for batch in data.batches(self.dataset, self.batch_size, seed=self.seed, epoch=epoch,
                                  start=index, part=self.part, keys=BATCH_KEYS):
          if self._stop.is_set():
            return
          self._queue.put(model_inputs(batch))
        step = (epoch + 1) * self.per_epoch
    except Exception as e:  # handed to the consumer, which raises it
      self._queue.put(e)

  def __next__(self):
    item = self._queue.get()
    if isinstance(item, Exception):
      raise item
    return sharding.global_batch(item, self.sharding)

  def close(self):
    self._stop.set()
    while not self._queue.empty():
      self._queue.get_nowait()
