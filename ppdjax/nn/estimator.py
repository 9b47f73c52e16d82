"""A density estimator that reads given boxes and their motion (Flax NNX).

The PPD generator guesses densities from one feature vector of the voxels, the image and
the trajectories, before it knows the boxes. Once the boxes are fitted (to the voxels and
the depth image), densities are a system-identification problem: given the geometry,
which masses make the object move as observed? `DensityEstimator` answers it directly:

  boxes (K, bottom to top): extents, centre, volume, valid  ─┐
  trajectories (P, T, 7) ─► per push: strided 1-D convolutions ─┴─► MLP ─► (K, 100) logits

It sees no image (materials are the generator's part; `combine_logits` joins the two), so
it trains on simulated towers without rendering (`ppdjax.dataset.physics_stream`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx

from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.nn.motion import TRAJ_FEATURES, trajectory_features
from ppdjax.primitives import Primitives, bottom_to_top_order

BOX_FEATURES = 8  # extents (3), centre (3), volume / 0.1 m^3, valid


def box_features(prims: Primitives) -> jax.Array:
  """(B, K, 8) the boxes' features in the order given (axis-aligned boxes: the quaternion
  is not read)."""
  ext = 2.0 * prims.half_size
  vol = jnp.prod(ext, -1, keepdims=True) / 0.1
  valid = prims.valid[..., None]
  feats = jnp.concatenate([ext, prims.pos, vol, valid.astype(ext.dtype)], -1)
  return jnp.where(valid, feats, 0.0)


class DensityEstimator(nnx.Module):
  """(boxes, trajectories) -> per-box logits over the 100 density slots.

  `config` is a preset's `estimator` section: channels (of the 1-D convolutions, each
  stride 2), hidden (MLP width), layers (MLP depth), steps_in (T the model reads),
  num_pushes, max_primitives.
  """

  def __init__(self, config: ml_collections.ConfigDict, *, rngs: nnx.Rngs):
    c = config
    self.k, self.p, self.steps_in = c.max_primitives, c.num_pushes, c.steps_in
    chans = (TRAJ_FEATURES,) + tuple(c.channels)
    self.convs = nnx.List([nnx.Conv(a, b, (5,), strides=(2,), rngs=rngs)
                           for a, b in zip(chans[:-1], chans[1:])])
    t_out = c.steps_in
    for _ in c.channels:
      t_out = -(-t_out // 2)
    self.traj_proj = nnx.Linear(c.num_pushes * t_out * chans[-1], c.hidden, rngs=rngs)
    self.box_proj = nnx.Linear(c.max_primitives * BOX_FEATURES, c.hidden, rngs=rngs)
    dims = [2 * c.hidden] + [c.hidden] * c.layers
    self.mlp = nnx.List([nnx.Linear(a, b, rngs=rngs) for a, b in zip(dims[:-1], dims[1:])])
    self.norms = nnx.List([nnx.LayerNorm(b, rngs=rngs) for b in dims[1:]])
    self.head = nnx.Linear(c.hidden, c.max_primitives * NUM_DENSITY_SLOTS, rngs=rngs)

  def encode_trajectories(self, traj_BPTx7: jax.Array) -> jax.Array:
    b, p, t = traj_BPTx7.shape[:3]
    if p != self.p or t != self.steps_in:
      raise ValueError(f"trajectories: expected (B, {self.p}, {self.steps_in}, 7), got "
                       f"{traj_BPTx7.shape}")
    x = trajectory_features(traj_BPTx7).reshape(b * p, t, TRAJ_FEATURES)
    for conv in self.convs:
      x = nnx.gelu(conv(x))
    return self.traj_proj(x.reshape(b, -1))

  def __call__(self, prims: Primitives, traj_BPTx7: jax.Array) -> jax.Array:
    """(B, K, 100) logits for boxes `prims` (B, K) in their given order (any order: they
    are read bottom to top and the logits put back); padded boxes get zeros."""
    if prims.valid.shape[-1] != self.k:
      raise ValueError(f"boxes: expected {self.k} slots, got {prims.valid.shape[-1]}")
    order = bottom_to_top_order(prims)
    feats = jnp.take_along_axis(box_features(prims), order[..., None], -2)
    x = jnp.concatenate([nnx.gelu(self.box_proj(feats.reshape(feats.shape[0], -1))),
                         nnx.gelu(self.encode_trajectories(traj_BPTx7))], -1)
    for lin, norm in zip(self.mlp, self.norms):
      x = nnx.gelu(norm(lin(x)))
    logits = self.head(x).reshape(-1, self.k, NUM_DENSITY_SLOTS)
    inverse = jnp.argsort(order, -1)
    logits = jnp.take_along_axis(logits, inverse[..., None], -2)
    return jnp.where(prims.valid[..., None], logits, 0.0)


def combine_logits(network_logits: jax.Array, estimator_logits: jax.Array,
                   weight: float) -> jax.Array:
  """Per-box scores of a product of experts: log softmax(network) + weight · log
  softmax(estimator). The network knows the material from the image, the estimator the
  mass from geometry and motion; weight 0 keeps the network's alone."""
  lsm = lambda x: jax.nn.log_softmax(x.astype(jnp.float32), -1)
  return lsm(network_logits) + weight * lsm(estimator_logits)


def slot_targets(slots_BK: jax.Array, sigma: float) -> jax.Array:
  """(B, K, 100) training targets: a Gaussian of width `sigma` slots about the true slot
  (one-hot when sigma is 0), so that near misses cost less than far ones."""
  if sigma <= 0:
    return jax.nn.one_hot(slots_BK, NUM_DENSITY_SLOTS)
  d = jnp.arange(NUM_DENSITY_SLOTS) - slots_BK[..., None]
  w = jnp.exp(-0.5 * (d / sigma) ** 2)
  return w / w.sum(-1, keepdims=True)
