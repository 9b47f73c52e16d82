"""Each box's density posterior, read from the candidates +Sample already simulated.

The S candidates are joint slot assignments drawn from the density scores; over the
distinct ones the posterior is p(slots) · likelihood, each assignment counted once (a
repeat, `sampling.Selection.distinct` False, weighs nothing: counted again it would square
the prior of a confident box). The
likelihood is exp(−(d − d_min) / T) in the trajectory distance d (metres,
`metrics.trajectory_distance`, over the selection's horizon): the selection objective
d − τ · log p is its negative log at T = τ. The noise scale is estimated per object, not
assumed: T = `scale` × d_min, the closest candidate's distance, which is what the
observations' noise and the boxes' misfit leave when the densities are right; `scale`,
one per box count (more boxes share one misfit), is chosen on validation towers
(docs/inference.md, "How sure each density is"). The density scores enter raised to
`prior_power` (< 1 widens what they say; the network is overconfident on tall towers).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax.conventions import NUM_DENSITY_SLOTS

MIN_DISTANCE = 1e-6  # m: the scale's floor where a candidate reproduces the motion exactly


@struct.dataclass
class DensityPosterior:
  """What the candidates say of each box's density slot (K boxes; batches lead).

  Attributes:
    probs: (K, 100) each box's marginal over the slots (zeros for padded boxes).
    mean: (K,) its mean slot (slot s is (s + 1) × 100 kg/m³).
    lower, upper: (K,) int32, the central interval of `PosteriorConfig.level` (both ends
      included).
    identified: (K,) the interval spans at most `PosteriorConfig.identified_width` slots
      beyond one, and at least two candidates were weighed (False for padded boxes).
    correlation: (K, K) the slots' correlation between boxes under the posterior (two
      boxes trading mass read near -1; 0 where a box is padded or certain).
    effective: () the candidates' effective number, 1 / Σ w²: near 1, one candidate
      explains the motion far better than every other.
  """

  probs: jax.Array
  mean: jax.Array
  lower: jax.Array
  upper: jax.Array
  identified: jax.Array
  correlation: jax.Array
  effective: jax.Array


def log_weights(distance_S, log_prior_S, scale: float, *, relative: bool = True):
  """(S,) normalised log weights log p(slots) − (d − d_min) / T, T = scale · d_min (or
  `scale` metres where not `relative`); candidates screened out (distance inf, or NaN)
  weigh nothing; an object without any finite distance gets its prior. Leading axes are
  objects. Works on NumPy arrays (float64, the evaluation's studies) and on JAX arrays
  (inside `decompose`)."""
  xp = jnp if isinstance(distance_S, jax.Array) else np
  finite = xp.isfinite(distance_S)
  some = xp.any(finite, -1, keepdims=True)
  d = xp.where(finite, distance_S, xp.inf)
  dmin = xp.where(some, xp.min(d, -1, keepdims=True), 0.0)
  t = scale * xp.maximum(dmin, MIN_DISTANCE) if relative else scale
  w = log_prior_S - xp.where(some, (d - dmin) / t, 0.0)
  w = w - xp.max(w, -1, keepdims=True)
  return w - xp.log(xp.sum(xp.exp(w), -1, keepdims=True))


def scale_for(scale, valid_K: jax.Array):
  """The temperature's scale of an object with `valid_K` boxes: `scale` itself, or of a
  sequence the entry of its box count (the last for more boxes)."""
  if np.ndim(scale) == 0:
    return scale
  table = jnp.asarray(scale, jnp.float32)
  return table[jnp.clip(jnp.sum(valid_K) - 1, 0, table.shape[0] - 1)]


def candidate_weights(distance_S: jax.Array, log_prior_S: jax.Array, valid_K: jax.Array, *,
                      scale, distinct_S: jax.Array | None = None, prior_power: float = 1.0):
  """(log weights (S,), temperature T ()) of one object's candidates under the posterior:
  the density scores raised to `prior_power`, repeats (`distinct_S` False) weighing
  nothing, T = the box count's scale × the closest finite distance."""
  log_prior_S = prior_power * log_prior_S
  if distinct_S is not None:
    log_prior_S = jnp.where(distinct_S, log_prior_S, -jnp.inf)
  scale = scale_for(scale, valid_K)
  closest = jnp.min(jnp.where(jnp.isfinite(distance_S), distance_S, jnp.inf))
  return (log_weights(distance_S, log_prior_S, scale),
          scale * jnp.maximum(closest, MIN_DISTANCE))


def interval(probs_Kx100: jax.Array, level: float) -> tuple[jax.Array, jax.Array]:
  """(lower, upper) (K,) slots of each marginal's central `level` interval: the first slot
  whose cumulative probability reaches (1 − level) / 2, and (1 + level) / 2."""
  cdf = jnp.cumsum(probs_Kx100, -1)
  tail = (1.0 - level) / 2.0
  lower = jnp.argmax(cdf >= tail - 1e-6, -1)
  upper = jnp.argmax(cdf >= 1.0 - tail - 1e-6, -1)
  return lower.astype(jnp.int32), upper.astype(jnp.int32)


def density_posterior(slots_SxK: jax.Array, distance_S: jax.Array, log_prior_S: jax.Array,
                      valid_K: jax.Array, *, scale: float, level: float,
                      identified_width: int, distinct_S: jax.Array | None = None,
                      prior_power: float = 1.0) -> DensityPosterior:
  """The posterior of one object's box slots over its candidates (`DensityPosterior`).

  Args:
    slots_SxK: the candidates' slots (`sampling.Selection.slots`).
    distance_S: their trajectory distances (inf where screened out).
    log_prior_S: their log-probabilities under the density scores (`sampling.log_prior`).
    valid_K: the boxes.
    scale: the likelihood's temperature over the closest candidate's distance: a number,
      or one per box count (the k-th for k + 1 valid boxes; the last for more).
    level: the intervals' probability (0.9: 90 % intervals).
    identified_width: the widest interval (upper − lower, slots) flagged identified.
    distinct_S: False for a candidate that repeats an earlier one (it weighs nothing);
      None: every candidate is distinct.
    prior_power: the density scores' log-probabilities are multiplied by it.
  """
  log_w, _ = candidate_weights(distance_S, log_prior_S, valid_K, scale=scale,
                               distinct_S=distinct_S, prior_power=prior_power)
  w = jnp.exp(log_w)  # (S,)
  weighed = jnp.sum(w > 0) >= 2
  one_hot = jax.nn.one_hot(slots_SxK, NUM_DENSITY_SLOTS)  # (S, K, 100)
  probs = jnp.where(valid_K[:, None], jnp.einsum("s,skn->kn", w, one_hot), 0.0)
  x = slots_SxK.astype(jnp.float32)
  mean = w @ x  # (K,)
  centred = x - mean
  cov = jnp.einsum("s,si,sj->ij", w, centred, centred)
  sd = jnp.sqrt(jnp.diag(cov))
  both = jnp.outer(sd, sd)
  live = (both > 1e-9) & valid_K[:, None] & valid_K[None, :]
  correlation = jnp.where(live, cov / jnp.where(live, both, 1.0), 0.0)
  lower, upper = interval(probs, level)
  return DensityPosterior(
      probs=probs, mean=jnp.where(valid_K, mean, 0.0), lower=lower, upper=upper,
      identified=valid_K & weighed & (upper - lower <= identified_width),
      correlation=correlation,
      effective=1.0 / jnp.sum(w ** 2))
