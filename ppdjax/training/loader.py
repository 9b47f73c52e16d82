"""Training batches read ahead in a thread, at a data position that is a function of the step."""

from __future__ import annotations

import queue
import threading

import jax

from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import batching
from ppdjax.training import sharding

BATCH_KEYS = OBS_KEYS + ("primitives",)  # what training reads from disk


def model_inputs(batch: dict) -> dict:
  """The arrays a step needs from a loader batch (observations and ground truth)."""
  return {k: batch[k] for k in BATCH_KEYS}


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
        for batch in batching.batches(self.dataset, self.batch_size, seed=self.seed, epoch=epoch,
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
