"""Evaluation metrics of paper Sec. 5.1: shape F1, density top-k accuracy and RMSE."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.primitives import Primitives, box_iou

IOU_THRESHOLD = 0.5


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


def f1_from_counts(matched, predicted, true) -> float:
  """Micro F1 (percent) over all boxes: 2·matched / (predicted + true)."""
  total = float(jnp.sum(predicted) + jnp.sum(true))
  return 100.0 * 2.0 * float(jnp.sum(matched)) / max(total, 1.0)


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
  """Dataset-level metrics from summed counts: top-k in percent, RMSE in slots, F1 in percent."""
  n = max(float(jnp.sum(counts["count"])), 1.0)
  out = {k: 100.0 * float(jnp.sum(v)) / n for k, v in counts.items() if k.startswith("top")}
  out["rmse"] = float(jnp.sqrt(jnp.sum(counts["sq_err"]) / n))
  if "matched" in counts:
    out["f1"] = f1_from_counts(counts["matched"], counts["predicted"], counts["true"])
  return out
