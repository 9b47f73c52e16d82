"""Shuffled batches of a dataset, one epoch at a time: deterministic in (seed, epoch),
resumable at any batch, read lazily through `storage.Dataset.take`."""

from __future__ import annotations

import numbers
from collections.abc import Iterator

import numpy as np


def _whole(name: str, value, low: int) -> None:
  if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral) or (
      value < low):
    raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")


def batches(dataset, batch_size: int, *, seed: int, epoch: int = 0,
            start: int = 0, drop_remainder: bool = True,
            part: tuple[int, int] = (0, 1), keys=None) -> Iterator[dict]:
  """Shuffled batches of one epoch, deterministic in (seed, epoch), read lazily.

  Args:
    dataset: a `storage.Dataset`.
    batch_size: samples per batch (an int >= 1); with drop_remainder, at most len(dataset).
    seed, epoch: ints >= 0; the permutation is `default_rng([seed, epoch]).permutation(len)`.
    start: first batch to yield (resume mid-epoch), at most the epoch's number of batches.
    drop_remainder: skip a last, smaller batch; False yields it (so a batch larger than
      the dataset gives one batch of all its samples).
    part: (i, n): read only the i-th of n equal slices of each batch (process i of n in a
      multi-host run); batch_size must divide by n.
    keys: sample keys to read (default all).

  Yields:
    dicts of stacked arrays (Primitives fields stacked too).

  Raises:
    ValueError naming the argument, before any read; with drop_remainder, a batch_size
    larger than the dataset (which would yield nothing) names both sizes.
  """
  for name, value, low in (("batch_size", batch_size, 1), ("seed", seed, 0),
                           ("epoch", epoch, 0), ("start", start, 0)):
    _whole(name, value, low)
  index, count = part
  if batch_size % count or not 0 <= index < count:
    raise ValueError(f"part={part} must split batch_size={batch_size} into equal slices")
  size = len(dataset)
  if drop_remainder and batch_size > size:
    raise ValueError(f"batch_size={batch_size} is larger than the {size} samples of "
                     f"{getattr(dataset, 'name', 'the dataset')}: not one full batch "
                     "(drop_remainder=False yields one smaller batch)")
  full = size // batch_size if drop_remainder else -(-size // batch_size)
  if start > full:
    raise ValueError(f"start={start} is past the {full} batches of an epoch of "
                     f"{size} samples at batch_size={batch_size}")
  order = np.random.default_rng([seed, epoch]).permutation(size)
  stop = size - (size % batch_size if drop_remainder else 0)
  for b in range(start * batch_size, stop, batch_size):
    rows = order[b:b + batch_size]
    rows = np.array_split(rows, count)[index] if count > 1 else rows
    yield dataset.take(rows, keys)
