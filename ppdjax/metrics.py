"""Evaluation metrics of paper Sec. 5.1: shape F1, density top-k and RMSE, trajectory error.

Trajectory units (the paper gives none): a pose error is the residual
[Δp; L · rotvec(q_sim ⊗ q_obs⁻¹)] in metres, with L = ROTATION_LENGTH = 0.5 m (half the
object's 1 m extent, so a rotation counts like the displacement it gives a point on the
object's bounding sphere). The reported trajectory MAE is the paper's literal
mean-absolute error over positions: mean over pushes, steps and x, y, z of |Δp|, in mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.box_overlap import box_iou
from ppdjax.primitives import Primitives, quat_mul

IOU_THRESHOLD = 0.5
ROTATION_LENGTH = 0.5  # m: a rotation of θ radians counts as θ · 0.5 m of displacement


def rotation_vector(q: jax.Array) -> jax.Array:
  """(..., 3) axis · angle (radians) of (..., 4) quaternions, either sign; differentiable."""
  q = q * jnp.where(q[..., :1] < 0, -1.0, 1.0)
  w, v = q[..., 0], q[..., 1:]
  n2 = jnp.sum(v * v, -1)
  n = jnp.sqrt(jnp.where(n2 > 1e-12, n2, 1.0))
  scale = jnp.where(n2 > 1e-12, 2.0 * jnp.arctan2(n, w) / n, 2.0 / jnp.maximum(w, 1e-6))
  return v * scale[..., None]


def relative_rotation(q_a: jax.Array, q_b: jax.Array) -> jax.Array:
  """(..., 3) rotvec(q_a ⊗ q_b⁻¹) in radians; its norm is the angle between the two
  orientations, exact for small angles (where the arccos of their float32 dot product
  rounds to zero below about 0.03°)."""
  return rotation_vector(quat_mul(q_a, q_b * jnp.array([1.0, -1.0, -1.0, -1.0])))


def pose_residual(sim_PTx7: jax.Array, obs_PTx7: jax.Array) -> jax.Array:
  """(..., 6) per-step residual [Δp; L · rotvec(q_sim ⊗ q_obs⁻¹)] in metres."""
  rot = relative_rotation(sim_PTx7[..., 3:], obs_PTx7[..., 3:])
  return jnp.concatenate([sim_PTx7[..., :3] - obs_PTx7[..., :3], ROTATION_LENGTH * rot], -1)


def trajectory_distance(sim_PTx7: jax.Array, obs_PTx7: jax.Array,
                        horizon: int = 0) -> jax.Array:
  """Mean over pushes and steps of the pose-error norm (metres): what sampling minimises.
  `horizon` > 0: over the first `horizon` steps only (0: all)."""
  return horizon_distances(sim_PTx7, obs_PTx7, (horizon,))[..., 0]


def horizon_distances(sim_PTx7: jax.Array, obs_PTx7: jax.Array,
                      horizons: tuple[int, ...]) -> jax.Array:
  """(..., H) `trajectory_distance` over the first h steps for each h of `horizons` (0 or
  more than T: all steps), from one residual computation."""
  r = pose_residual(sim_PTx7, obs_PTx7)
  err = jnp.sqrt(jnp.sum(r * r, -1) + 1e-12).mean(-2)  # (..., T) mean over pushes
  t = err.shape[-1]
  ends = [t if h <= 0 or h > t else h for h in horizons]
  cum = jnp.cumsum(err, -1)
  return jnp.stack([cum[..., e - 1] / e for e in ends], -1)


def trajectory_mae(sim_PTx7: jax.Array, obs_PTx7: jax.Array) -> jax.Array:
  """The paper's trajectory MAE: mean |Δp| over pushes, steps and x, y, z, in millimetres."""
  return 1000.0 * jnp.abs(sim_PTx7[..., :3] - obs_PTx7[..., :3]).mean((-3, -2, -1))


def match_boxes(pred: Primitives, true: Primitives, threshold: float = IOU_THRESHOLD,
                grid: int = 32) -> jax.Array:
  """Greedy one-to-one matching by IoU; (...,) number of matched pairs with IoU > threshold.

  Pairs are taken in decreasing IoU and each box is used once. Ground-truth boxes do not
  overlap, so a predicted box can exceed IoU 0.5 with at most one of them and greedy
  matching is the maximum matching.
  """
  iou = box_iou(pred, true, grid)  # (..., K, L)
  iou = jnp.where(iou > threshold, iou, 0.0)

  def take(carry, _):
    iou, count = carry
    flat = iou.reshape(iou.shape[:-2] + (-1,))
    best = jnp.argmax(flat, axis=-1)
    hit = jnp.take_along_axis(flat, best[..., None], -1)[..., 0] > 0
    row, col = best // iou.shape[-1], best % iou.shape[-1]
    keep_row = jnp.arange(iou.shape[-2]) != row[..., None]
    keep_col = jnp.arange(iou.shape[-1]) != col[..., None]
    iou = iou * keep_row[..., :, None] * keep_col[..., None, :]
    return (iou, count + hit), None

  count = jnp.zeros(iou.shape[:-2], jnp.int32)
  (_, count), _ = jax.lax.scan(take, (iou, count), None, length=min(iou.shape[-2:]))
  return count


def shape_counts(pred: Primitives, true: Primitives, grid: int = 32) -> dict:
  """Per-object counts for F1: matched, predicted and true boxes, each (...,)."""
  return {"matched": match_boxes(pred, true, grid=grid),
          "predicted": pred.valid.sum(-1), "true": true.valid.sum(-1)}


FACE_NAMES = ("x lo", "y lo", "z lo", "x hi", "y hi", "z hi")


def box_faces(prims: Primitives):
  """(..., K, 6) faces pos ∓ half size along the object frame's axes (`FACE_NAMES`)."""
  return jnp.concatenate([prims.pos - prims.half_size, prims.pos + prims.half_size], -1)


def face_errors(pred: Primitives, true: Primitives) -> jax.Array:
  """(..., K, 6) metres: |face − true face| of the k-th box against the k-th true box (both
  in the order given; pass them bottom to top), faces as pos ∓ half size along the object
  frame's axes (`FACE_NAMES`); NaN where either box is missing. Exact for axis-aligned
  boxes (the block towers); for turned boxes it mixes position and size errors."""
  both = (pred.valid & true.valid)[..., None]
  return jnp.where(both, jnp.abs(box_faces(pred) - box_faces(true)), jnp.nan)


def f1_from_counts(matched, predicted, true) -> float:
  """Micro F1 (percent) over all boxes: 2·matched / (predicted + true). On the host (NumPy:
  the bootstrap calls it a thousand times)."""
  total = float(np.sum(predicted) + np.sum(true))
  return 100.0 * 2.0 * float(np.sum(matched)) / max(total, 1.0)


def density_counts(slot_logits: jax.Array, true_slot: jax.Array, valid: jax.Array,
                   ks=(1, 5, 10)) -> dict:
  """Per-primitive density hits, summed per object.

  Args:
    slot_logits: (..., K, 100) scores over density slots for the k-th primitive.
    true_slot: (..., K) ground-truth slots; primitives correspond by position (both are
      ordered bottom to top).
    valid: (..., K) which ground-truth primitives exist.
    ks: top-k accuracies to count.

  Returns:
    dict of (...,) sums: "top{k}" hits, "sq_err" (squared slot error of the arg-max),
    "count" (valid primitives).
  """
  own = jnp.take_along_axis(slot_logits, true_slot[..., None], -1)
  earlier = jnp.arange(slot_logits.shape[-1]) < true_slot[..., None]
  # ties rank like arg-max does: the lower slot first
  rank = jnp.sum((slot_logits > own) | ((slot_logits == own) & earlier), -1)
  out = {f"top{k}": jnp.sum((rank < k) & valid, -1) for k in ks}
  err = jnp.argmax(slot_logits, -1) - true_slot
  out["sq_err"] = jnp.sum(jnp.where(valid, err * err, 0), -1)
  out["count"] = jnp.sum(valid, -1)
  return out


def summarize(counts: dict) -> dict:
  """Dataset-level metrics from summed counts: top-k in percent, RMSE in slots, F1 in percent
  (on the host, in NumPy)."""
  counts = {k: np.asarray(v) for k, v in counts.items()}
  n = max(float(np.sum(counts["count"])), 1.0)
  out = {k: 100.0 * float(np.sum(v)) / n for k, v in counts.items() if k.startswith("top")}
  out["rmse"] = float(np.sqrt(np.sum(counts["sq_err"], dtype=np.float64) / n))
  if "matched" in counts:
    out["f1"] = f1_from_counts(counts["matched"], counts["predicted"], counts["true"])
  return out


def bootstrap_interval(stat, num_objects: int, *, resamples: int = 1000, level: float = 0.95,
                       seed: int = 0, groups=None) -> tuple[float, float]:
  """Percentile bootstrap interval of a dataset-level statistic over objects.

  Args:
    stat: maps an index array into the evaluated objects (with repeats) to a float, e.g.
      F1 from the per-object counts it selects.
    num_objects: how many objects were evaluated.
    resamples: bootstrap resamples.
    level: the interval's coverage.
    seed: of the resampling.
    groups: None (objects drawn with replacement), or a (num_objects,) array of group
      ids: then whole groups are drawn with replacement (a cluster bootstrap), as many as
      there are groups. The configurations of a tower or tool share its shape, so their
      scores are not independent: resampling them one by one narrows the interval.
      Groups of one object each draw exactly what the object bootstrap draws.

  Returns:
    (low, high), the (1 − level)/2 and (1 + level)/2 quantiles of the resampled statistic.
  """
  if num_objects < 1:
    raise ValueError(f"a bootstrap needs at least one object, got {num_objects}")
  rng = np.random.default_rng(seed)
  if groups is None:
    draw = lambda: rng.integers(0, num_objects, num_objects)
  else:
    groups = np.asarray(groups)
    if groups.shape != (num_objects,):
      raise ValueError(f"groups must hold one id per object, shape ({num_objects},), got "
                       f"{groups.shape}")
    _, inverse = np.unique(groups, return_inverse=True)
    sizes = np.bincount(inverse)
    starts = np.cumsum(sizes) - sizes  # of each group in the objects sorted by group
    order = np.argsort(inverse, kind="stable")
    members = np.full((len(sizes), sizes.max()), -1)  # (groups, largest), -1 padded
    members[inverse[order], np.arange(num_objects) - starts[inverse[order]]] = order

    def draw():
      idx = members[rng.integers(0, len(sizes), len(sizes))].ravel()
      return idx[idx >= 0]
  values = np.array([stat(draw()) for _ in range(resamples)], np.float64)
  lo, hi = np.quantile(values, [(1 - level) / 2, (1 + level) / 2])
  return float(lo), float(hi)
