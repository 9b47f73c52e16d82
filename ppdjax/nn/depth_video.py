"""The RGB-D row's physics encoder (paper Table 2): a raw depth video of each push in place
of its 3D trajectory, encoded to f_T as the trajectory encoder does.

Each frame goes through a small convolutional network (four 3 x 3 convolutions of stride
2, LeakyReLU(0.2), flattened to FRAME_FEATURES); each push's frames then through a forward
and a backward LSTM of its own, as a push's poses go through the trajectory encoder's
(`model.TrajectoryEncoder`), and [h->; h<-] of every push are projected to f_T. Depth is
read raw: clipped to NEAR..FAR_CLIP metres (the sky's 100 m would swamp the object's few
centimetres of change) and centred on the camera's distance to the scene.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from ppdjax.nn.recurrent import GroupedLSTM, per_push_bidirectional

FRAME_FEATURES = 64  # per frame, into the LSTMs
CHANNELS = (16, 32, 64, 64)  # the four stride-2 convolutions (S / 16 pixels left per side)
NEAR, FAR_CLIP = 1.0, 5.0  # m: the scene lies between (the camera is 2.6 m from its target)
CENTRE, SPREAD = 3.0, 2.0  # m: clipped depth -> (depth - CENTRE) / SPREAD in [-1, 1]


class DepthVideoEncoder(nnx.Module):
  """(B, P, F, S, S) depth videos -> f_T (B, out_features)."""

  def __init__(self, num_pushes: int, size: int, hidden: int, out_features: int,
               dropout: float, *, rngs: nnx.Rngs, unroll: int = 1):
    if size % 16:
      raise ValueError(f"config.model.video_size must be a multiple of 16, got {size}")
    chans = (1,) + CHANNELS
    self.convs = nnx.List([nnx.Conv(a, b, (3, 3), strides=(2, 2), rngs=rngs)
                           for a, b in zip(chans[:-1], chans[1:])])
    self.frame = nnx.Linear(CHANNELS[-1] * (size // 16) ** 2, FRAME_FEATURES, rngs=rngs)
    self.lstm = GroupedLSTM(2 * num_pushes, FRAME_FEATURES, hidden, rngs=rngs, unroll=unroll)
    self.dropout = nnx.Dropout(dropout)
    self.proj = nnx.Linear(2 * num_pushes * hidden, out_features, rngs=rngs)

  def frame_features(self, video_BPFSS: jax.Array) -> jax.Array:
    """(B, P, F, FRAME_FEATURES): each frame through the convolutions."""
    b, p, f, s, _ = video_BPFSS.shape
    x = (jnp.clip(video_BPFSS.astype(jnp.float32), NEAR, FAR_CLIP) - CENTRE) / SPREAD
    x = x.reshape(b * p * f, s, s, 1)
    for conv in self.convs:
      x = nnx.leaky_relu(conv(x), 0.2)
    x = nnx.leaky_relu(self.frame(x.reshape(x.shape[0], -1)), 0.2)
    return x.reshape(b, p, f, -1)

  def __call__(self, video_BPFSS: jax.Array, train: bool, rngs) -> jax.Array:
    h = per_push_bidirectional(self.lstm, self.frame_features(video_BPFSS))
    return self.proj(self.dropout(h, deterministic=not train, rngs=rngs))
