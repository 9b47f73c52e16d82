"""Training targets and the loss of paper Eq. 4–5: L1 geometry + w × density cross-entropy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

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


def loss_fn(pred: Prediction, tgt: dict, density_weight) -> tuple[jax.Array, dict]:
  """L = L_G + w · L_P, summed over a sequence's steps and averaged over the batch.

  L_G: L1 of size, translation and rotation (weights 1, as in the paper) over the true
  boxes; L_P: cross-entropy of the 102-way density head over the boxes and the end token.
  """
  l1 = lambda a, b: jnp.abs(a - b).sum(-1)
  geometry = (l1(pred.half_size, tgt["half_size"]) + l1(pred.pos, tgt["pos"])
              + l1(pred.quat, tgt["quat"]))
  geometry = jnp.where(tgt["geometry_mask"], geometry, 0.0).sum(-1).mean()
  ce = optax.softmax_cross_entropy_with_integer_labels(pred.density_logits, tgt["token"])
  density = jnp.where(tgt["density_mask"], ce, 0.0).sum(-1).mean()
  loss = geometry + density_weight * density
  return loss, {"loss": loss, "geometry_loss": geometry, "density_loss": density}
