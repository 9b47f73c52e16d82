"""+Sample (paper Sec. 4.3): draw joint density assignments, simulate them, keep the best.

The network proposes boxes and, per box, a distribution over the 100 density slots.
`select_densities` draws joint assignments from it, simulates each under the pushes and
keeps the one that minimises `selection_objective` (the trajectory distance, optionally
less τ · log prior). Distances and units: `ppdjax.metrics` (pose residual in metres,
rotations at 0.5 m per radian).

Mass-matched selection (`mass_match`, ours): the distance is stiff in an object's total
mass and soft in how the mass is split between its boxes
(experiments/results/selection_study), so on the 100 kg/m³ grid the closest candidate is
the one with the best total, whatever its split. A second pass scales every candidate to
the total mass of the closest one and simulates them again: then the distance compares
splits. The answer's densities are continuous (off the slot grid).

Screened selection (`screen_steps`, ours): every candidate is simulated over the first
`screen_steps` steps only, the `screen_keep` closest over that prefix are simulated over
the whole trajectory, and the winner is chosen among them (`screen_survivors`). At 32
steps and 64 of 512 that is 3.2× fewer simulated steps; how often it keeps the exhaustive
winner is measured by the evaluation (`rows.screen_records`, docs/inference.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax import metrics
from ppdjax.conventions import (MAX_DENSITY, MIN_DENSITY, NUM_DENSITY_SLOTS,
                                density_to_slot_jax, slot_to_density_jax)
from ppdjax.infer import faces
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, Settings, simulate


@struct.dataclass
class Selection:
  """What sampling found for one object (S candidates, K boxes).

  Attributes:
    density: (K,) kg/m^3 of the best candidate (scaled to the matched mass with
      `mass_match`).
    score: trajectory distance of the best candidate (metres, `metrics.trajectory_distance`).
    scores: (S,) every candidate's distance, in draw order (candidate 0 is the most likely);
      inf for a candidate screened out over the prefix (`screen_steps`).
    slots: (S, K) the candidates' density slots (0 for padded boxes).
    distinct: (S,) False for a candidate that repeats an earlier one (small supports).
    mae: (S,) every candidate's trajectory MAE (mm, `metrics.trajectory_mae`; inf where
      screened out).
    trajectories: (P, T, 7) the best candidate simulated under the pushes.
    best: index of the best candidate.
    boxes: (S, K) every candidate's boxes (the given boxes unless faces were drawn,
      `face_spread`) with its slots' densities.
  """

  density: jax.Array
  score: jax.Array
  scores: jax.Array
  slots: jax.Array
  distinct: jax.Array
  mae: jax.Array
  trajectories: jax.Array
  best: jax.Array
  boxes: Primitives


def candidate_slots(logits_Kx100: jax.Array, valid_K: jax.Array, num_samples: int,
                    key: jax.Array, *, include_mode: bool = True,
                    oversample: int = 2) -> tuple[jax.Array, jax.Array]:
  """`num_samples` joint slot assignments drawn from independent per-box categoricals.

  Candidate 0 is the arg-max of every box when `include_mode`. `oversample` × as many are
  drawn; the first occurrence of each distinct assignment is kept in draw order, so the
  result has no duplicates unless the distribution's support is smaller than asked for.

  Returns:
    (slots (S, K) int32 with 0 for padded boxes, distinct (S,) bool).
  """
  k = logits_Kx100.shape[0]
  m = max(num_samples * oversample, num_samples)
  draws = jax.random.categorical(key, logits_Kx100, shape=(m, k)).astype(jnp.int32)
  if include_mode:
    draws = draws.at[0].set(jnp.argmax(logits_Kx100, -1).astype(jnp.int32))
  draws = jnp.where(valid_K, draws, 0)
  duplicate = repeats(draws, NUM_DENSITY_SLOTS)
  index = jnp.arange(m)
  take = jnp.argsort(jnp.where(duplicate, m + index, index))[:num_samples]
  return draws[take], ~duplicate[take]


def repeats(values_MxK: jax.Array, base: int) -> jax.Array:
  """(M,) True for each row of integers in [0, base) that repeats an earlier row."""
  m, k = values_MxK.shape
  per_code = max(1, int(np.log(2 ** 31 - 1) // np.log(base)))  # digits in one int32 code
  # Lexicographic sort by the rows' codes, then row index: the first of each run of equal
  # rows is the earliest.
  codes = [sum(values_MxK[:, j] * base ** (j - c) for j in range(c, min(c + per_code, k)))
           for c in range(0, k, per_code)]
  index = jnp.arange(m)
  order = jnp.lexsort([index] + codes[::-1])
  sorted_codes = jnp.stack([c[order] for c in codes], -1)
  repeat = jnp.concatenate([jnp.zeros(1, bool),
                            jnp.all(sorted_codes[1:] == sorted_codes[:-1], -1)])
  return jnp.zeros(m, bool).at[order].set(repeat)


def candidate_boxes(prims: Primitives, slots_SxK: jax.Array, key: jax.Array,
                    face_spread: float = 0.0) -> Primitives:
  """Candidates (S, K): `prims` (K) with each row of slots' densities; with `face_spread`
  > 0 (voxels) each candidate's faces drawn too (`faces.spread_faces`, from `key`)."""
  out = with_slots(prims, slots_SxK)
  if face_spread > 0:
    moved = faces.spread_faces(prims, key, slots_SxK.shape[0], face_spread)
    out = moved.replace(density=out.density)
  return out


def log_prior(logits_Kx100: jax.Array, slots_SxK: jax.Array, valid_K: jax.Array) -> jax.Array:
  """(S,) log-probability of each joint assignment under the per-box categoricals."""
  lp = jax.nn.log_softmax(logits_Kx100[:, :NUM_DENSITY_SLOTS], -1)
  per_box = jnp.take_along_axis(lp[None], slots_SxK[..., None], -1)[..., 0]
  return jnp.sum(jnp.where(valid_K, per_box, 0.0), -1)


def with_slots(prims: Primitives, slots: jax.Array) -> Primitives:
  """`prims` (K) with densities from slots (..., K); leading axes are broadcast."""
  batch = slots.shape[:-1]
  grow = lambda x: jnp.broadcast_to(x, batch + x.shape)
  out = jax.tree.map(grow, prims)
  return out.replace(density=slot_to_density_jax(slots))


def total_mass(prims: Primitives) -> jax.Array:
  """(...,) kg: Σ density · volume over the valid boxes (overlaps counted twice)."""
  volume = jnp.prod(2.0 * prims.half_size, -1)
  return jnp.sum(jnp.where(prims.valid, prims.density * volume, 0.0), -1)


def scale_to_mass(prims: Primitives, mass: jax.Array) -> Primitives:
  """`prims` (..., K) with every valid box's density times mass / total_mass, within the
  slot range [100, 10,000] kg/m³ (a clipped box leaves the total off)."""
  scale = mass / jnp.maximum(total_mass(prims), 1e-12)
  scaled = jnp.clip(prims.density * scale[..., None], MIN_DENSITY, MAX_DENSITY)
  return prims.replace(density=jnp.where(prims.valid, scaled, prims.density))


def match_closest_mass(candidates: Primitives, distance: jax.Array) -> Primitives:
  """Candidates (S, K) scaled to the total mass of the one at the least distance (S,): the
  second pass of mass-matched selection."""
  return scale_to_mass(candidates, total_mass(candidates)[jnp.argmin(distance)])


def score_candidates(candidates: Primitives, observed_PTx7: jax.Array, pushes: Pushes,
                     settings: Settings = DEFAULT_SETTINGS, *,
                     keep_trajectories: bool = False, horizons: tuple[int, ...] = ()):
  """(distance (S,), MAE (S,)[, trajectories (S, P, T, 7)]) of candidates (S, K).

  With `horizons`, distance is (S, H): over the first h steps for each h (0: all steps;
  `metrics.horizon_distances`)."""
  steps = observed_PTx7.shape[-2]

  def one(p):
    sim = simulate(p, pushes, steps=steps, settings=settings)
    dist = (metrics.horizon_distances(sim, observed_PTx7, horizons) if horizons
            else metrics.trajectory_distance(sim, observed_PTx7))
    scores = (dist, metrics.trajectory_mae(sim, observed_PTx7))
    return scores + (sim,) if keep_trajectories else scores
  return jax.vmap(one)(candidates)


def screen_survivors(candidates: Primitives, observed_PTx7: jax.Array, pushes: Pushes,
                     settings: Settings = DEFAULT_SETTINGS, *, steps: int,
                     keep: int) -> jax.Array:
  """(keep,) indices of the candidates (S, K) closest to the observation over its first
  `steps` steps (`metrics.trajectory_distance` over the prefix), closest first: the
  screen of screened selection. Simulates S × P rollouts of `steps` steps."""
  dist, _ = score_candidates(candidates, observed_PTx7[..., :steps, :], pushes, settings)
  return jax.lax.top_k(-dist, keep)[1]


def check_screen(screen_steps: int, screen_keep: int, num_samples: int, steps: int) -> bool:
  """Raises ValueError for a screen that cannot run; True when it screens anything (a
  prefix shorter than the trajectory and fewer survivors than candidates)."""
  if screen_steps < 0 or screen_keep < 1:
    raise ValueError(f"screen_steps must be >= 0 (0: no screen) and screen_keep >= 1, got "
                     f"{screen_steps} and {screen_keep}")
  return 0 < screen_steps < steps and screen_keep < num_samples


def check_selection_horizon(selection_horizon: int) -> None:
  """Raises ValueError unless `selection_horizon` is a step count >= 0 (0: all steps)."""
  if isinstance(selection_horizon, bool) or not isinstance(selection_horizon, (int, np.integer)) \
      or selection_horizon < 0:
    raise ValueError(f"selection_horizon must be a whole number of steps >= 0 (0: all), got "
                     f"{selection_horizon!r}")


def selection_objective(distance: jax.Array, log_prior_: jax.Array,
                        prior_weight: float) -> jax.Array:
  """What +Sample minimises: distance (m) − τ · log prior (nats); τ = 0 is the paper's."""
  return distance - prior_weight * log_prior_


def select_densities(prims: Primitives, density_logits: jax.Array, observed: jax.Array,
                     pushes: Pushes | None = None, *, num_samples: int, key: jax.Array,
                     include_mode: bool = True, prior_weight: float = 0.0,
                     mass_match: bool = False, screen_steps: int = 0,
                     screen_keep: int = 64, face_spread: float = 0.0,
                     selection_horizon: int = 0, whole_scores: bool = True,
                     settings: Settings = DEFAULT_SETTINGS) -> Selection:
  """Samples joint density assignments and keeps the one that best explains the motion.

  Args:
    prims: predicted geometry of one object (K boxes; densities ignored).
    density_logits: (K, 100) scores over density slots per box (the network's head).
    observed: (P, T, 7) observed trajectories.
    pushes: the P pushes (None: the paper's four).
    num_samples: candidates S (all simulated in one batched call).
    key: PRNG key.
    include_mode: make candidate 0 the most likely assignment.
    prior_weight: τ in metres per nat: the winner minimises distance − τ · log p(slots)
      under the network's distribution (0: the paper's closest trajectory).
    mass_match: a second pass (twice the rollouts): every candidate scaled to the total
      mass of the closest one (`scale_to_mass`), simulated again, and the winner chosen
      among those by the same objective (its log prior at the nearest slots).
    screen_steps: > 0 screens the candidates over their first `screen_steps` steps and
      simulates only the `screen_keep` closest over the whole trajectory
      (`screen_survivors`); the winner is chosen among them (0: every candidate whole, the
      paper's). With `mass_match`, the second pass runs on the survivors.
    screen_keep: survivors of the screen.
    face_spread: > 0 draws each candidate's faces too, uniform within this many voxels of
      the given ones (`faces.spread_faces`; candidate 0 keeps them): for boxes fitted to
      voxels, which place a face only within half a voxel (`faces.VOXEL_TOLERANCE`).
    selection_horizon: > 0 picks the winner (and, with `mass_match`, the mass it matches)
      by the distance over the first this many steps (`metrics.trajectory_distance(
      horizon=)`; 0, or the trajectory's length or more: all steps, the paper's). The
      returned scores stay whole-trajectory distances. With a screen, the winner is the
      best of its survivors over this horizon. A Python int (it shapes the program).
    whole_scores: with a horizon shorter than the trajectory, False simulates the
      candidates over the horizon only (the pick is the same; `horizon` / T of the
      steps) and the winner alone over every step: `scores` and `mae` are then
      distances over the horizon, `score` and `trajectories` still the winner's whole.
    settings: the engine's settings (MJX, box-plane or MuJoCo C: `rollout_mjx.Settings`).

  Returns:
    Selection: best densities, its score and every candidate's score and MAE.
  """
  pushes = default_pushes() if pushes is None else pushes
  faces.check_spread(face_spread)
  check_selection_horizon(selection_horizon)
  slots, distinct = candidate_slots(density_logits[:, :NUM_DENSITY_SLOTS], prims.valid,
                                    num_samples, key, include_mode=include_mode)
  candidates = candidate_boxes(prims, slots, jax.random.fold_in(key, 1), face_spread)
  logp = log_prior(density_logits, slots, prims.valid)
  screened = check_screen(screen_steps, screen_keep, num_samples, observed.shape[-2])
  survivors = (screen_survivors(candidates, observed, pushes, settings, steps=screen_steps,
                                keep=screen_keep) if screened else jnp.arange(num_samples))
  kept = jax.tree.map(lambda x: x[survivors], candidates) if screened else candidates
  steps = observed.shape[-2]
  short = not whole_scores and 0 < selection_horizon < steps
  # each candidate's distance over all steps (column 0) and over the selection horizon;
  # `short`: both over the horizon, the only steps simulated
  seen = observed[..., :selection_horizon, :] if short else observed
  score = lambda boxes: score_candidates(boxes, seen, pushes, settings, keep_trajectories=True,
                                         horizons=(0, 0 if short else selection_horizon))
  dists, err, sims = score(kept)
  kept_logp = logp[survivors] if screened else logp
  if mass_match:  # the mass of the closest by the same rule as the winner's
    kept = match_closest_mass(kept, dists[:, 1])
    dists, err, sims = score(kept)
    kept_logp = log_prior(density_logits, density_to_slot_jax(kept.density), prims.valid)
  dist = dists[:, 0]
  best = jnp.argmin(selection_objective(dists[:, 1], kept_logp, prior_weight))
  everyone = lambda x: (jnp.full((num_samples,), jnp.inf, x.dtype).at[survivors].set(x)
                        if screened else x)
  winner_score, winner_sim = dist[best], sims[best]
  if short:  # the winner alone over every step
    winner = jax.tree.map(lambda x: x[best][None], kept)
    whole, _, whole_sim = score_candidates(winner, observed, pushes, settings,
                                           keep_trajectories=True)
    winner_score, winner_sim = whole[0], whole_sim[0]
  return Selection(density=kept.density[best], score=winner_score, scores=everyone(dist),
                   slots=slots, distinct=distinct, mae=everyone(err),
                   trajectories=winner_sim, best=survivors[best], boxes=candidates)
