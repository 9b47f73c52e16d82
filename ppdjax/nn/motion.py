"""What the networks read of a trajectory: normalised per-step features and early motion."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import TIMESTEP
from ppdjax.primitives import quat_mul

TRAJ_FEATURES = 10
SPEED_SCALE = 0.1  # m/s (and rad/s for early_motion's spin); see compress


def compress(x: jax.Array) -> jax.Array:
  """sign(x)·log(1 + |x| / 0.1): speeds span two decades (0.1-10 m/s)."""
  return jnp.sign(x) * jnp.log1p(jnp.abs(x) / SPEED_SCALE)


def decompress(y) -> np.ndarray:
  """The inverse of `compress`, in NumPy (float64)."""
  y = np.asarray(y, np.float64)
  return np.sign(y) * np.expm1(np.abs(y)) * SPEED_SCALE


def trajectory_features(traj_BPTx7: jax.Array) -> jax.Array:
  """Normalised trajectory inputs (B, P, T, 10): [p_t − p_0, q_t, compressed velocity].

  Positions are taken relative to the first recorded pose (metres; towers move up to
  about a metre). The velocity (p_t − p_{t−1}) / dt carries the density signal — the
  push's impulse over the mass — over two decades, so it is compressed (`compress`).
  Quaternions are already in [−1, 1].
  """
  pos, quat = traj_BPTx7[..., :3], traj_BPTx7[..., 3:]
  vel = jnp.diff(pos, axis=-2, prepend=pos[..., :1, :]) / TIMESTEP
  return jnp.concatenate([pos - pos[..., :1, :], quat, compress(vel)], -1)


def early_motion(traj_BPTx7: jax.Array, steps: int) -> jax.Array:
  """(B, P · steps · 6) the linear and angular velocity (world frame) between recorded
  poses 0..`steps` of each push, each compressed (`compress`; m/s, rad/s). Pose 0 is the
  one after the push's step, so the first velocity is that of the simulation's second
  step (the rest pose before the push is not in a trajectory).

  What a push does at once is where a body's mass, centre of mass and inertia show most
  plainly (Δv = J/m, Δω = I⁻¹ (r − c) × J): within one tool's density configurations these
  velocities alone give each part's density to about 1 % (docs/data.md), while the
  motion that follows mixes in friction and contacts. The trajectory LSTM sees the linear
  velocity among 256 steps and the rotation only as quaternions that change by 1e-4 a
  step; these features hand both to the density branch directly.
  """
  pos, quat = traj_BPTx7[:, :, :steps + 1, :3], traj_BPTx7[:, :, :steps + 1, 3:]
  vel = jnp.diff(pos, axis=2) / TIMESTEP
  delta = quat_mul(quat[:, :, 1:], quat[:, :, :-1] * jnp.array([1., -1, -1, -1]))
  delta = delta * jnp.where(delta[..., :1] < 0, -1.0, 1.0)  # the short way round
  spin = 2 * delta[..., 1:] / TIMESTEP
  x = compress(jnp.concatenate([vel, spin], -1))
  return x.reshape(x.shape[0], -1)
