"""Training targets and the loss of paper Eq. 4–5: L1 geometry + the end token + w × density."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.conventions import density_to_slot_jax
from ppdjax.nn.model import END, START, Prediction, primitive_vector
from ppdjax.primitives import Primitives, bottom_to_top, canonical_boxes


def targets(prims: Primitives) -> dict:
  """What the generator must emit for a batch of ground truth (B, K).

  Boxes are ordered bottom to top and given their canonical label
  (`primitives.canonical_boxes`). The sequence has S = K + 1 steps: the n boxes, then the
  end token.

  Returns:
    dict with "token" (B, S) density slot or END, "density_mask" (B, S) (steps ≤ n),
    "geometry_mask" (B, S) (steps < n), "half_size"/"pos"/"quat" (B, S, ·), "prev"
    (B, S, 112) the teacher-forced inputs (start token, then the true boxes), "slot" (B, K).
  """
  prims = canonical_boxes(bottom_to_top(prims))
  b, k = prims.density.shape
  n = prims.valid.sum(-1)
  steps = jnp.arange(k + 1)
  slot = density_to_slot_jax(prims.density)
  pad = lambda x: jnp.concatenate([x, jnp.zeros_like(x[:, :1])], 1)
  token = jnp.where(steps < n[:, None], pad(slot), END)
  start = primitive_vector(jnp.full((b, 1), START), jnp.zeros((b, 1, 3)),
                           jnp.zeros((b, 1, 3)), jnp.zeros((b, 1, 4)))
  prev = primitive_vector(token[:, :k], prims.half_size, prims.pos, prims.quat)
  return {
      "token": token, "slot": slot,
      "density_mask": steps <= n[:, None], "geometry_mask": steps < n[:, None],
      "half_size": pad(prims.half_size), "pos": pad(prims.pos), "quat": pad(prims.quat),
      "prev": jnp.concatenate([start, prev], 1),
  }


def loss_fn(pred: Prediction, tgt: dict, density_weight, *, end_weight=1.0,
            geometry_weight=1.0) -> tuple[jax.Array, dict]:
  """L = g · L_G + e · L_E + w · L_D, summed over a sequence's steps and averaged over the batch.

  L_G: L1 of size, translation and rotation (weights 1, as in the paper) over the true
  boxes. The paper's density loss, the 102-way cross-entropy over the boxes and the end
  token, splits exactly into L_E + L_D: L_E = −log p(stop or go) (a binary cross-entropy,
  "is this step the end token?") and L_D = −log p(slot | not the end) over the true boxes.
  With e = w the sum is the paper's loss; with e > 0 the box count learns in every phase,
  also while w = 0 (the paper's geometry phase, the geometry stream), where the
  density slots must not learn.
  """
  l1 = lambda a, b: jnp.abs(a - b).sum(-1)
  geometry = (l1(pred.half_size, tgt["half_size"]) + l1(pred.pos, tgt["pos"])
              + l1(pred.quat, tgt["quat"]))
  geometry = jnp.where(tgt["geometry_mask"], geometry, 0.0).sum(-1).mean()
  logp = jax.nn.log_softmax(pred.density_logits)
  log_end = logp[..., END]
  log_go = jnp.log(-jnp.expm1(jnp.minimum(log_end, -1e-7)))  # log(1 - p(end)), stable
  is_end = tgt["token"] == END
  end = jnp.where(tgt["density_mask"], -jnp.where(is_end, log_end, log_go), 0.0).sum(-1).mean()
  own = jnp.take_along_axis(logp, tgt["token"][..., None], -1)[..., 0]
  density = jnp.where(tgt["geometry_mask"], log_go - own, 0.0).sum(-1).mean()
  loss = geometry_weight * geometry + end_weight * end + density_weight * density
  return loss, {"loss": loss, "geometry_loss": geometry, "end_loss": end,
                "density_loss": density}
