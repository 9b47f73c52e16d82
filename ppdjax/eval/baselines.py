"""Baselines of paper Tables 2 and 4, as rankings over the 100 density slots per box.

Table 2's baselines assume the ground-truth shape (boxes ordered bottom to top) and
differ in how they rank slots:

* Frequent: every box gets the training set's slot frequencies.
* Nearest: the training objects with the same number of blocks whose trajectories are
  closest (`trajectory_features`); box k ranks slots by the first neighbour whose k-th
  box has them, then by frequency.
* Oracle: knows each box's material and ranks that material's slots in a random order
  (a uniform guess within its range), then the rest by frequency.

A ranking is returned as scores (B, K, 100) (higher is better), so `metrics.density_counts`
scores baselines and the network alike; the arg-max is the baseline's guess.

Table 4's sampling baselines ("Sample Phys.", "Sample Phys.+Shape") draw densities
uniformly (and shapes from the tower distribution, `random_shapes`); `evaluate` scores
them with the same physics as the network's samples.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import NUM_DENSITY_SLOTS, NUM_SLOTS, density_to_slot
from ppdjax.dataset import storage, stream
from ppdjax.dataset.materials import ALL_MATERIAL_NAMES, material_slots
from ppdjax.metrics import ROTATION_LENGTH, rotation_vector
from ppdjax.primitives import Primitives, bottom_to_top_order

FEATURE_STRIDE = 8  # trajectory steps between retrieval features
NEIGHBOURS = 10  # neighbours a Nearest ranking looks at


def true_slots(prims: Primitives) -> np.ndarray:
  """(B, K) density slots bottom to top (-1 for padding)."""
  order = np.asarray(bottom_to_top_order(prims))
  slot = np.take_along_axis(density_to_slot(np.asarray(prims.density)), order, -1)
  return np.where(np.take_along_axis(np.asarray(prims.valid), order, -1), slot, -1)


def true_materials(prims: Primitives, materials) -> np.ndarray:
  """(B, K) material ids (`materials.ALL_MATERIAL_NAMES`) bottom to top, as `true_slots`
  orders the slots (-1 for padding)."""
  order = np.asarray(bottom_to_top_order(prims))
  ids = np.take_along_axis(np.asarray(materials), order, -1)
  return np.where(np.take_along_axis(np.asarray(prims.valid), order, -1), ids, -1)


def trajectory_features(traj_BxPxTx7: np.ndarray) -> np.ndarray:
  """(B, D) float32 poses every FEATURE_STRIDE steps, [p, L·rotvec(q)] in metres.

  Squared Euclidean distance between features approximates the squared pose residual
  that sampling minimises (`metrics.pose_residual`), at 1/FEATURE_STRIDE the cost.
  """
  t = np.asarray(traj_BxPxTx7, np.float32)[:, :, FEATURE_STRIDE - 1::FEATURE_STRIDE]
  rot = np.asarray(rotation_vector(t[..., 3:]))
  return np.concatenate([t[..., :3], ROTATION_LENGTH * rot], -1).reshape(len(t), -1)


class TrainingSet:
  """What the Frequent and Nearest baselines know: slot frequencies and trajectory features."""

  def __init__(self, dataset: storage.Dataset, *, max_samples: int = 0, chunk: int = 2048,
               progress: bool = True):
    n = len(dataset) if not max_samples else min(max_samples, len(dataset))
    feats, slots = [], []
    for start in tqdm(range(0, n, chunk), desc="reading the training split", unit="chunk",
                      disable=not progress):
      part = dataset.take(np.arange(start, min(start + chunk, n)),
                          keys=("trajectories", "primitives"))
      feats.append(trajectory_features(part["trajectories"]))
      slots.append(true_slots(part["primitives"]))
    self.features = np.concatenate(feats)
    self.slots = np.concatenate(slots)  # (N, K) bottom to top, -1 padding
    self.num_blocks = (self.slots >= 0).sum(-1)
    counts = np.bincount(self.slots[self.slots >= 0], minlength=NUM_DENSITY_SLOTS)
    self.frequency = counts / max(counts.sum(), 1)
    self._sq_norm = (self.features.astype(np.float64) ** 2).sum(-1)

  def frequency_scores(self) -> np.ndarray:
    """(100,) a ranking by frequency; ties broken towards lower slots (as arg-max does)."""
    return self.frequency - 1e-9 * np.arange(NUM_DENSITY_SLOTS)

  def neighbours(self, traj_BxPxTx7: np.ndarray, num_blocks_B: np.ndarray,
                 count: int = NEIGHBOURS) -> np.ndarray:
    """(B, count) training indices closest in trajectory with the same block count (-1: none)."""
    f = trajectory_features(traj_BxPxTx7).astype(np.float64)
    d = (f ** 2).sum(-1)[:, None] - 2.0 * f @ self.features.T.astype(np.float64) + self._sq_norm
    d = np.where(self.num_blocks[None] == np.asarray(num_blocks_B)[:, None], d, np.inf)
    take = min(count, d.shape[1])
    idx = np.argsort(d, axis=-1)[:, :take]
    idx = np.where(np.isfinite(np.take_along_axis(d, idx, -1)), idx, -1)
    return np.pad(idx, ((0, 0), (0, count - take)), constant_values=-1)


def frequent_scores(train: TrainingSet, batch: int, k: int = NUM_SLOTS) -> np.ndarray:
  """(B, K, 100) the Frequent ranking for every box."""
  return np.broadcast_to(train.frequency_scores(), (batch, k, NUM_DENSITY_SLOTS)).copy()


def nearest_scores(train: TrainingSet, traj_BxPxTx7: np.ndarray,
                   num_blocks_B: np.ndarray) -> np.ndarray:
  """(B, K, 100) the Nearest ranking: the neighbours' slots in neighbour order, then frequency."""
  idx = train.neighbours(traj_BxPxTx7, num_blocks_B)  # (B, N)
  b, n = idx.shape
  k = train.slots.shape[1]
  scores = frequent_scores(train, b, k)  # in [0, 1]
  neigh = np.where(idx[..., None] >= 0, train.slots[np.maximum(idx, 0)], -1)  # (B, N, K)
  for j in reversed(range(n)):  # the nearest neighbour writes last, so it wins
    s = neigh[:, j]  # (B, K)
    bb, kk = np.nonzero(s >= 0)
    scores[bb, kk, s[bb, kk]] = 2.0 + (n - j)
  return scores


def oracle_scores(train: TrainingSet, materials_BxK: np.ndarray, prims: Primitives,
                  seed: int) -> np.ndarray:
  """(B, K, 100) the Oracle ranking: the true material's slots in a random order first.

  Args:
    train: for the frequency order of the remaining slots.
    materials_BxK: material ids (indices into ALL_MATERIAL_NAMES, -1 padding) in box order.
    prims: the ground truth (to order boxes bottom to top).
    seed: the random guesses are a function of (seed, object, box).
  """
  order = np.asarray(bottom_to_top_order(prims))
  mats = np.take_along_axis(np.asarray(materials_BxK), order, -1)
  b, k = mats.shape
  scores = frequent_scores(train, b, k)
  rng = np.random.default_rng(seed)
  for i in range(b):
    for j in range(k):
      if mats[i, j] >= 0:
        slots = material_slots(ALL_MATERIAL_NAMES[mats[i, j]])
        scores[i, j, slots] = 2.0 + rng.permutation(len(slots))
  return scores


def baseline_scores(train: TrainingSet, batch: dict, oracle_seed: int) -> np.ndarray:
  """(B, 3, K, 100) Frequent, Nearest and Oracle slot scores (`tables.BASELINES` order) for
  a batch with "primitives", "trajectories" and "materials"."""
  slot = true_slots(batch["primitives"])
  return np.stack([frequent_scores(train, len(slot), slot.shape[1]),
                   nearest_scores(train, batch["trajectories"], (slot >= 0).sum(-1)),
                   oracle_scores(train, batch["materials"], batch["primitives"], oracle_seed)],
                  1)


@functools.partial(jax.jit, static_argnums=(1, 2))
def random_shapes(key: jax.Array, count: int, num_slots: int = NUM_SLOTS) -> Primitives:
  """`count` tower shapes of the dataset's distribution (2..K blocks; placeholder
  densities), drawn on the accelerator by `stream.sample_towers_jax`: the NumPy generator
  took about 5 s for the 512 shapes of an evaluation batch, longer than the batch's
  device work."""
  return stream.sample_towers_jax(key, count, num_slots)
