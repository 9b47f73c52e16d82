"""Which push to make next: each candidate push scored by its expected information gain.

Given a decomposition, the posterior's most probable joint density assignments (the
hypotheses, `infer.posterior`) are simulated under every candidate push in one batched
call. A push is informative where the hypotheses disagree about the motion it would cause.
Its expected information gain, with the posterior's own likelihood exp(−d / T) between
trajectories (d the trajectory distance, T the posterior's temperature), is

    EIG = −Σ_i w_i log Σ_j w_j exp(−d(y_i, y_j) / T),

in nats: 0 where every hypothesis moves alike, up to the posterior's entropy where each
moves apart from every other. The estimator treats each hypothesis' simulated motion as
what would be observed (noise enters through T only).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax import metrics
from ppdjax.infer import sampling
from ppdjax.infer.posterior import candidate_weights
from ppdjax.sim.pushes import PAPER_FORCE, Pushes
from ppdjax.sim.rollout_mjx import simulate

# The paper's four pushes come from (±1, −1, ±1) towards the origin: azimuths −45° and
# −135° about z, elevations ±35.26° (atan(1 / √2)) above and below the horizontal.
PAPER_ELEVATION = float(np.degrees(np.arctan(1.0 / np.sqrt(2.0))))


@struct.dataclass
class PushChoice:
  """Candidate pushes scored for one object (N candidates; batches lead).

  Attributes:
    gain: (N,) expected information gain of each candidate push (nats).
    best: () index of the most informative.
    hypotheses: () how many joint assignments were simulated (the weight's top ones).
  """

  gain: jax.Array
  best: jax.Array
  hypotheses: jax.Array


def candidate_pushes(azimuths: int = 8, elevations=(-PAPER_ELEVATION, PAPER_ELEVATION),
                     strengths=(0.25, 0.5, 1.0, 2.0), magnitude: float = PAPER_FORCE,
                     distance: float = float(np.sqrt(3.0))) -> Pushes:
  """A grid of pushes aimed at the object-frame origin: `azimuths` directions about z
  (every 360° / azimuths from −135°, so the paper's −45° and −135° are among them) ×
  `elevations` (degrees) × `strengths` (times `magnitude`), each from `distance` metres.
  The default's 64 hold the paper's four (`paper_push_indices`)."""
  az = np.radians(-135.0 + 360.0 / azimuths * np.arange(azimuths))
  el = np.radians(np.asarray(elevations, np.float64))
  a, e, s = (x.ravel() for x in np.meshgrid(az, el, np.asarray(strengths, np.float64),
                                              indexing="ij"))
  sources = distance * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
  return Pushes(sources=sources.astype(np.float32), targets=np.zeros_like(sources, np.float32),
                magnitudes=(s * magnitude).astype(np.float32), duration=1).validate()


def paper_push_indices(candidates: Pushes, paper: Pushes) -> np.ndarray:
  """(P,) the index among `candidates` of each of `paper`'s pushes; raises ValueError if
  one is not there."""
  c = np.concatenate([np.asarray(candidates.sources, np.float64) /
                      np.linalg.norm(candidates.sources, axis=-1, keepdims=True),
                      np.asarray(candidates.magnitudes, np.float64)[:, None] / PAPER_FORCE], -1)
  p = np.concatenate([np.asarray(paper.sources, np.float64) /
                      np.linalg.norm(paper.sources, axis=-1, keepdims=True),
                      np.asarray(paper.magnitudes, np.float64)[:, None] / PAPER_FORCE], -1)
  dist = np.linalg.norm(c[None] - p[:, None], axis=-1)
  index = dist.argmin(-1)
  if np.any(dist[np.arange(len(p)), index] > 1e-4):
    raise ValueError("a push of `paper` is not among the candidates")
  return index


def push_gains(prims, slots_SxK, distance_S, log_prior_S, candidates: Pushes, *,
               hypotheses: int, scale: float, steps: int, settings,
               distinct_S=None, prior_power: float = 1.0) -> PushChoice:
  """`PushChoice` of one object: its boxes `prims` (K), its +Sample candidates (slots,
  distances, log prior; repeats, `distinct_S` False, weigh nothing) and the pushes to
  score (N), simulated over `steps` steps; the posterior's settings as
  `posterior.density_posterior`'s."""
  w, t = candidate_weights(distance_S, log_prior_S, prims.valid, scale=scale,
                           distinct_S=distinct_S, prior_power=prior_power)
  top_w, top = jax.lax.top_k(w, hypotheses)
  w_h = jax.nn.softmax(top_w)  # the top hypotheses' weights, renormalised
  boxes = sampling.with_slots(prims, slots_SxK[top])  # (H, K)
  traj = simulate(boxes, candidates, steps=steps, settings=settings)  # (H, N, steps, 7)
  gain = information_gain(traj, w_h, t)  # t: the posterior's T
  return PushChoice(gain=gain, best=jnp.argmax(gain), hypotheses=jnp.asarray(hypotheses))


def information_gain(traj_HxNxTx7: jax.Array, weights_H: jax.Array,
                     temperature: jax.Array) -> jax.Array:
  """(N,) the expected information gain (nats) of each of N pushes, from the H weighted
  hypotheses' simulated motion under each (`traj_HxNxTx7`) and the posterior's T."""
  h = traj_HxNxTx7.shape[0]
  per_push = jnp.swapaxes(traj_HxNxTx7, 0, 1)[:, :, None]  # (N, H, 1, T, 7): one push each
  pairwise = lambda y: jax.vmap(lambda a: jax.vmap(
      lambda b: metrics.trajectory_distance(a, b))(y))(y)  # (H, H)
  d = jax.lax.map(pairwise, per_push)  # (N, H, H), one push at a time: H² trajectories
  d = jnp.where(jnp.eye(h, dtype=bool), 0.0, d)  # the metric's floor: 1e-6 m
  mix = jax.scipy.special.logsumexp(-d / temperature, axis=-1,
                                    b=weights_H[None, None, :])  # (N, H)
  return -jnp.sum(weights_H[None] * mix, -1)


def make_next_push_fn(decompose, candidates: Pushes | None = None, *, hypotheses: int = 32):
  """One jitted `next_push(decomposition) -> PushChoice` beside a `decompose`.

  Args:
    decompose: what `make_decompose_fn` returned (its settings: the posterior's scale, the
      candidates' engine, the selection's horizon).
    candidates: the pushes to choose among (None: `candidate_pushes()`, 64 with the
      paper's four).
    hypotheses: the posterior's most probable joint assignments simulated under each
      candidate: hypotheses × N rollouts (32 × 64 is one `decompose` call's 512 × 4).

  Returns:
    next_push(decomposition): a `PushChoice` for one object or a batch (leading B), its
    pushes simulated over the steps the posterior's distances cover (the selection's
    horizon, else the observed trajectories' length).
  """
  candidates = candidate_pushes() if candidates is None else candidates.validate()
  config = decompose.config
  if (isinstance(hypotheses, bool) or not isinstance(hypotheses, (int, np.integer))
      or hypotheses < 2):
    raise ValueError(f"hypotheses must be a whole number >= 2, got {hypotheses!r}")
  if config.select.samples < 2:
    raise ValueError("choosing a push weighs the posterior's candidates: select.samples "
                     f"must be >= 2, got {config.select.samples}")
  if config.select.mass_match:
    raise ValueError("select.mass_match scores mass-scaled candidates, not the drawn slots "
                     "the hypotheses would simulate: choose pushes without it")
  horizon = config.select.horizon if not config.refine.enabled else 0

  @jax.jit
  def run(dec):
    steps = dec.trajectories.shape[-2]
    steps = horizon if 0 < horizon < steps else steps
    count = min(int(hypotheses), dec.candidates.shape[-2])
    logp = jax.vmap(sampling.log_prior)(dec.density_logits, dec.candidates,
                                        dec.primitives.valid)
    return jax.vmap(lambda p, s, d, l, u: push_gains(
        p, s, d, l, candidates, hypotheses=count, scale=config.posterior.scale, steps=steps,
        settings=decompose.settings, distinct_S=u,
        prior_power=config.posterior.prior_power))(dec.primitives, dec.candidates,
                                                    dec.scores, logp, dec.distinct)

  def next_push(decomposition) -> PushChoice:
    batched = np.ndim(decomposition.scores) == 2
    dec = decomposition if batched else jax.tree.map(lambda x: x[None], decomposition)
    out = run(dec)
    return out if batched else jax.tree.map(lambda x: x[0], out)

  next_push.candidates = candidates
  return next_push
