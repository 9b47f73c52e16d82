"""Which objects an evaluation takes, and its batches read ahead of the computation."""

from __future__ import annotations

import concurrent.futures
import time

import numpy as np


def evaluation_objects(total: int, max_objects: int = 0, subset: str = "first") -> np.ndarray:
  """Indices of the objects to evaluate: all, the first N, or N spread evenly ("spread")."""
  if subset not in ("first", "spread"):
    raise ValueError(f"subset must be 'first' or 'spread', got {subset!r}")
  if max_objects < 0:
    raise ValueError(f"max_objects must be >= 0, got {max_objects}")
  n = total if not max_objects else min(max_objects, total)
  if subset == "first" or n == total:
    return np.arange(n)
  return np.unique(np.linspace(0, total - 1, n).round().astype(np.int64))


def table4_batches(sizes, table4_objects: int) -> np.ndarray:
  """Indices of the batches (of `sizes` objects each) that simulate Table 4's sampling
  baselines: batches spread evenly over the evaluation, together at least `table4_objects`
  objects (0, or more than there are: all)."""
  sizes = np.asarray(sizes)
  if table4_objects < 0:
    raise ValueError(f"table4_objects must be >= 0 (0: every object), got {table4_objects}")
  if not table4_objects or table4_objects >= sizes.sum():
    return np.arange(len(sizes))
  want = -(-table4_objects // sizes.max())
  while True:
    chosen = np.unique(np.linspace(0, len(sizes) - 1, want).round().astype(np.int64))
    if sizes[chosen].sum() >= table4_objects:
      return chosen
    want += 1


def read_ahead(read, starts, prefetch: bool):
  """(start, read(start)) for each start; with `prefetch`, the next batch is read in a
  background thread while the caller computes the current one (reading 64 objects' images
  and depth from disk takes about 1 s on an H100 machine). The time spent waiting for a
  read is added to `read.waited`."""
  starts = list(starts)
  read.waited = 0.0
  with concurrent.futures.ThreadPoolExecutor(1) as pool:
    future = pool.submit(read, starts[0]) if prefetch and starts else None
    for i, start in enumerate(starts):
      t = time.perf_counter()
      item = future.result() if prefetch else read(start)
      read.waited += time.perf_counter() - t
      if prefetch and i + 1 < len(starts):
        future = pool.submit(read, starts[i + 1])
      yield start, item
