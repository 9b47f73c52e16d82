"""+Search (ours): +Sample iterated, each round drawing near the closest candidates so far.

+Sample draws every candidate from the density scores. Where the scores say little (blocks
that look alike) and a tower has four boxes, 512 joint draws rarely land near the densities
that explain the motion, and refinement, a local method, does not reach them from there
(experiments/video_identifiability). A search in the spirit of the cross-entropy method
closes part of that gap: round 0 draws `samples` candidates from the scores as +Sample does
(with a key of its own); each later round draws as many by moving the elite, the
`ELITE` × `samples` candidates closest so far: a random elite candidate, each box's slot
moved with probability MOVE_SHARE by a Gaussian step in log density that narrows round by
round (WIDTHS), a box redrawn from the scores with probability SCORES_MIX so that no slot
is ever ruled out.

With `inertia`, each candidate's boxes also carry an inertia scale
(`Primitives.inertia_scale`: a hollow or filled block's inertia over a uniform one's), one
of INERTIA_LEVELS, moved by a Gaussian step LEVEL_WIDTH levels wide: the shells that solid
boxes cannot stand for (`dataset.hollow`).

With `continuation`, the elite of round r is chosen over the trajectories' first
continuation × 2^r steps (`continuation_horizons`), then over the selection horizon: a
strike's first steps are smooth in the densities, the fall that follows is not, so the
early rounds follow the smooth part and the later ones the rest. The winner is always the
least over the selection horizon.

The rounds run in one `jax.lax.scan` (one compiled round); every round's candidates are
returned, `samples × rounds` in all, so that the posterior weighs them all.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import NUM_DENSITY_SLOTS, density_to_slot_jax, slot_to_density_jax
from ppdjax.infer import sampling
from ppdjax.infer.refine import INERTIA_SCALE_RANGE
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, Settings

ELITE = 1 / 16  # the elite's size over a round's: the closest this many candidates so far
SCORES_MIX = 0.1  # the chance that a later round redraws a box from the density scores
# The steps' widths in log density of rounds 1, 2, ...: wide enough at first to move a
# box to a neighbouring material, a few per cent at the end; the last holds for later rounds.
WIDTHS = (0.4, 0.2, 0.1, 0.05)
# The inertia scales a candidate's box may take (geometric, 1 among them: a uniform box).
INERTIA_LEVELS = tuple(float(x) for x in np.geomspace(*INERTIA_SCALE_RANGE, 9))
UNIFORM_SHARE = 0.5  # round 0's share of a uniform box (scale 1); the rest on every level
LEVEL_WIDTH = 1.0  # the inertia levels' step in later rounds
MOVE_SHARE = 0.5  # the chance that a box's slot (its level) moves in a later round's step


def check_rounds(rounds: int) -> None:
  """Raises ValueError unless `rounds` is a whole number >= 1 (1: +Sample alone)."""
  if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 1:
    raise ValueError(f"select.rounds must be a whole number >= 1 (1: +Sample alone), got "
                     f"{rounds!r}")


def check_continuation(first: int, rounds: int, selection_horizon: int) -> None:
  """Raises ValueError unless `first` (select.continuation) is a whole number >= 0 and,
  above 0, schedules something: rounds > 1 and shorter than a selection horizon."""
  if isinstance(first, bool) or not isinstance(first, (int, np.integer)) or first < 0:
    raise ValueError(f"select.continuation must be a whole number >= 0 (0: none), got "
                     f"{first!r}")
  if first and 0 < selection_horizon <= first:
    raise ValueError(f"select.continuation ({first} steps in round 0) must be shorter than "
                     f"select.horizon ({selection_horizon}), or it schedules nothing")
  if first and rounds < 2:
    raise ValueError("select.continuation schedules +Search's rounds: it needs "
                     f"select.rounds > 1, got {rounds}")


def continuation_horizons(first: int, rounds: int, selection_horizon: int,
                          steps: int) -> tuple[int, ...]:
  """(rounds,) the steps each round's elite is compared over: `first` in round 0, doubling
  each round until it reaches the selection horizon (0: all `steps`), which the rest
  keep; `first` 0: the selection horizon throughout (`check_continuation`'s errors)."""
  check_continuation(first, rounds, selection_horizon)
  end = selection_horizon if 0 < selection_horizon < steps else steps
  if first == 0:
    return (selection_horizon,) * rounds
  return tuple(first * 2 ** r if first * 2 ** r < end else selection_horizon
               for r in range(rounds))


def perturb(parents_ExK: jax.Array, width: jax.Array, count: int, key: jax.Array, *,
            size: int, log_density: bool) -> jax.Array:
  """(count, K) levels in [0, size): each row a random parent's, every entry moved by a
  Gaussian step `width` wide: in log density for slots (a step of 10 % is a slot near
  1,000 kg/m³ and ten near 10,000, as the motion tells masses apart by their ratios),
  else in levels. Moving whole candidates keeps what their boxes trade between them (two
  boxes on a ridge of equal mass), which per-box marginals would lose."""
  pick, step = jax.random.split(key)
  parents = parents_ExK[jax.random.randint(pick, (count,), 0, parents_ExK.shape[0])]
  step, which = jax.random.split(step)
  noise = width * jax.random.normal(step, parents.shape)
  noise = jnp.where(jax.random.uniform(which, parents.shape) < MOVE_SHARE, noise, 0.0)
  if log_density:
    moved = density_to_slot_jax(slot_to_density_jax(parents) * jnp.exp(noise))
  else:
    moved = jnp.round(parents + noise)
  return jnp.clip(moved, 0, size - 1).astype(jnp.int32)


def initial_inertia(k: int) -> jax.Array:
  """(K, levels) round 0's inertia proposal: UNIFORM_SHARE on a uniform box (scale 1), the
  rest spread over every level (1 among them)."""
  n = len(INERTIA_LEVELS)
  p = np.full(n, (1 - UNIFORM_SHARE) / n)
  p[int(np.argmin(np.abs(np.log(INERTIA_LEVELS))))] += UNIFORM_SHARE
  return jnp.log(jnp.broadcast_to(jnp.asarray(p, jnp.float32), (k, n)))


def search_densities(prims: Primitives, density_logits: jax.Array, observed: jax.Array,
                     pushes: Pushes, *, num_samples: int, rounds: int, key: jax.Array,
                     inertia: bool = False, prior_weight: float = 0.0,
                     selection_horizon: int = 0, continuation: int = 0,
                     settings: Settings = DEFAULT_SETTINGS) -> sampling.Selection:
  """+Search: `rounds` rounds of `num_samples` candidates (module docstring), the winner the
  least `sampling.selection_objective` (over the selection horizon) among all of them.

  Args:
    prims: the geometry of one object (K boxes; densities ignored).
    density_logits: (K, 100) the density scores (round 0's proposal and the prior).
    observed: (P, T, 7) the observed trajectories.
    pushes: the P pushes.
    num_samples, rounds: candidates per round, and rounds (1: +Sample's draw alone).
    key: PRNG key.
    inertia: candidates carry inertia scales (INERTIA_LEVELS), searched beside the slots.
    prior_weight, selection_horizon: as `sampling.select_densities`.
    continuation: > 0: round r's elite is chosen over the first continuation × 2^r steps
      (`continuation_horizons`); 0: over the selection horizon in every round.
    settings: the engine's settings.

  Returns:
    sampling.Selection over all `num_samples × rounds` candidates, in round order (`boxes`
    carry inertia scales with `inertia`).
  """
  check_rounds(rounds)
  sampling.check_selection_horizon(selection_horizon)
  logits = density_logits[:, :NUM_DENSITY_SLOTS]
  k, n_levels = logits.shape[0], len(INERTIA_LEVELS)
  level_values = jnp.asarray(INERTIA_LEVELS, jnp.float32)
  elite = max(1, int(round(ELITE * num_samples)))
  pool = min(elite, num_samples)
  # each round's elite horizon; the elite carries its cost at every one of them, so that a
  # round compares its candidates and the elite over the same steps
  round_horizons = continuation_horizons(continuation, rounds, selection_horizon,
                                         observed.shape[-2])

  def candidates(slots, levels):
    boxes = sampling.with_slots(prims, slots)
    if inertia:
      boxes = boxes.replace(inertia_scale=jnp.where(prims.valid, level_values[levels], 1.0))
    return boxes

  def one_round(carry, xs):
    best_slots, best_levels, best_costs = carry
    round_key, width, first, index = xs
    keys = jax.random.split(round_key, 5)
    drawn, _ = sampling.candidate_slots(logits, prims.valid, num_samples, keys[0])
    first_levels = jax.random.categorical(keys[1], initial_inertia(k), shape=(num_samples, k))
    # later rounds: the elite's candidates moved, a box at a time redrawn from the scores
    redraw = jax.random.uniform(keys[2], (num_samples, k)) < SCORES_MIX
    moved = jnp.where(redraw, drawn, perturb(best_slots, width, num_samples, keys[3],
                                             size=NUM_DENSITY_SLOTS, log_density=True))
    moved_levels = perturb(best_levels, LEVEL_WIDTH, num_samples, keys[4], size=n_levels,
                           log_density=False)
    slots = jnp.where(prims.valid, jnp.where(first, drawn, moved), 0)
    levels = jnp.where(prims.valid, jnp.where(first, first_levels, moved_levels), 0)
    dist, err, sims = sampling.score_candidates(
        candidates(slots, levels), observed, pushes, settings, keep_trajectories=True,
        horizons=(0, selection_horizon) + round_horizons)
    costs = sampling.selection_objective(  # (S, 1 + rounds): the winner's, each round's
        dist[:, 1:], sampling.log_prior(logits, slots, prims.valid)[:, None], prior_weight)
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)  # a rollout that blew up: never
    cost = costs[:, 0]
    # the elite: the closest of this round's candidates and the elite so far, over the
    # round's horizon
    all_costs = jnp.concatenate([best_costs, costs[:, 1:]])
    keep = jax.lax.top_k(-all_costs[:, index], pool)[1]
    carry = (jnp.concatenate([best_slots, slots])[keep],
             jnp.concatenate([best_levels, levels])[keep], all_costs[keep])
    # the round's closest trajectory only: the winner's, whichever round it comes from
    return carry, (slots, levels, dist[:, 0], err, cost, sims[jnp.argmin(cost)])

  widths = jnp.asarray([WIDTHS[min(max(r - 1, 0), len(WIDTHS) - 1)] for r in range(rounds)],
                       jnp.float32)
  start = (jnp.zeros((pool, k), jnp.int32), jnp.zeros((pool, k), jnp.int32),
           jnp.full((pool, rounds), jnp.inf))
  _, (slots, levels, dist, err, cost, round_sims) = jax.lax.scan(
      one_round, start, (jax.random.split(key, rounds), widths, jnp.arange(rounds) == 0,
                         jnp.arange(rounds)))
  flat = lambda x: x.reshape((rounds * num_samples,) + x.shape[2:])  # noqa: E731
  slots, levels, dist, err, cost = map(flat, (slots, levels, dist, err, cost))
  distinct = ~sampling.repeats(slots * n_levels + levels if inertia else slots,
                               NUM_DENSITY_SLOTS * (n_levels if inertia else 1))
  best = jnp.argmin(cost)  # the first least: the least of its round
  boxes = candidates(slots, levels)
  return sampling.Selection(
      density=boxes.density[best], score=dist[best],
      scores=jnp.where(jnp.isfinite(dist), dist, jnp.inf), slots=slots, distinct=distinct,
      mae=err, trajectories=round_sims[best // num_samples], best=best, boxes=boxes)
