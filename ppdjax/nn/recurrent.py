"""The recurrent units of the PPD network: LSTMs stepped by hand (the generator) and many
independent LSTMs stepped together over time (the trajectory and depth-video encoders)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx


def _lstm_update(z, c):
  i, f, g, o = jnp.split(z, 4, axis=-1)
  c = nnx.sigmoid(f) * c + nnx.sigmoid(i) * jnp.tanh(g)
  return c, nnx.sigmoid(o) * jnp.tanh(c)


class GroupedLSTM(nnx.Module):
  """G independent single-layer LSTMs stepped together; one `lax.scan` over time.

  The trajectory encoder runs a forward and a backward LSTM for each of the P pushes
  (G = 2P), each with its own weights, as one batched recurrence. `unroll` steps run per
  iteration of the scan (the same arithmetic; fewer loop iterations on an accelerator).
  """

  def __init__(self, groups: int, in_features: int, hidden: int, *, rngs: nnx.Rngs,
               unroll: int = 1):
    init = nnx.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=0)
    ortho = nnx.initializers.orthogonal(column_axis=-1)
    self.wx = nnx.Param(init(rngs.params(), (groups, in_features, 4 * hidden)))
    self.wh = nnx.Param(jax.vmap(lambda k: ortho(k, (hidden, 4 * hidden)))(
        jax.random.split(rngs.params(), groups)))
    bias = jnp.zeros((groups, 4, hidden)).at[:, 1].set(1.0)  # forget gate starts open
    self.b = nnx.Param(bias.reshape(groups, 4 * hidden))
    self.hidden, self.unroll = hidden, unroll

  def __call__(self, x_BGTxF: jax.Array) -> jax.Array:
    """Final hidden states (B, G, H) of each group over its (B, G, T, F) sequence."""
    xw = jnp.einsum("bgtf,gfk->tgbk", x_BGTxF, self.wx.value) + self.b.value[:, None]
    wh = self.wh.value
    b, g = x_BGTxF.shape[:2]

    def step(carry, xw_t):  # group-major (G, B, ·): a batched matmul over groups
      c, h = carry
      return _lstm_update(xw_t + jnp.einsum("gbh,ghk->gbk", h, wh), c), None

    zeros = jnp.zeros((g, b, self.hidden), xw.dtype)
    (_, h), _ = jax.lax.scan(step, (zeros, zeros), xw, unroll=self.unroll)
    h = jnp.swapaxes(h, 0, 1)
    return h


class LSTMCell(nnx.Module):
  """One LSTM layer stepped by hand (the generator runs S ≤ 6 steps)."""

  def __init__(self, in_features: int, hidden: int, *, rngs: nnx.Rngs):
    self.x = nnx.Linear(in_features, 4 * hidden, rngs=rngs,
                        bias_init=lambda k, s, d=jnp.float32: jnp.zeros(s, d).at[
                            hidden:2 * hidden].set(1.0))
    self.h = nnx.Linear(hidden, 4 * hidden, use_bias=False,
                        kernel_init=nnx.initializers.orthogonal(), rngs=rngs)

  def __call__(self, carry, x):
    c, h = carry
    c, h = _lstm_update(self.x(x) + self.h(h), c)
    return (c, h), h


def per_push_bidirectional(lstm: GroupedLSTM, x_BPTxF: jax.Array) -> jax.Array:
  """(B, P * 2H): [h->_k; h<-_k] of each push's sequence through its own forward and
  backward LSTM (`lstm` has 2P groups: the forward ones, then the backward ones)."""
  p = x_BPTxF.shape[1]
  h = lstm(jnp.concatenate([x_BPTxF, x_BPTxF[:, :, ::-1]], axis=1))  # (B, 2P, H)
  return jnp.stack([h[:, :p], h[:, p:]], 2).reshape(h.shape[0], -1)
