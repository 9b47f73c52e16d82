"""Refinement inside the closed loop: after each push, the loop's answer refined on the
pushes made so far, as the depth preset's `decompose` refines the closest candidate.

The loop's answers are the closest candidates over the pushes made, compared over the
selection's horizon (`run.closed_loop`); Levenberg-Marquardt (`infer.refine`) then fits
the densities to the whole trajectories of those pushes and keeps the fit only where it
comes closer (`refine_if_closer`, the rule `decompose` and the evaluation share); with a prior, the
MAP step under the prior model's density scores, kept where its cost fell.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax import metrics
from ppdjax.conventions import density_to_slot_jax, slot_to_density_jax
from ppdjax.infer.refine import refine_if_closer
from ppdjax.sim.rollout_mjx import simulate


def refine_on(prims, answer, made, observed, pushes, *, steps: int, jacobian: str, settings,
              prior=None, prior_weight=0.0):
  """One answer (K slots) refined on the pushes `made` ((k,) indices, k static): the
  refinement (`Refinement`) and the slots kept (refined where it came closer)."""
  sub = jax.tree.map(lambda a: jnp.asarray(a)[made], pushes)
  obs = observed[made]
  start = prims.replace(density=slot_to_density_jax(answer))
  distance = metrics.trajectory_distance(
      simulate(start, sub, steps=obs.shape[-2], settings=settings), obs)
  r = refine_if_closer(start, obs, distance, sub, steps=steps, jacobian=jacobian,
                       settings=settings, prior=prior, prior_weight=prior_weight)
  return r, jnp.where(r.closer, density_to_slot_jax(r.primitives.density), answer)


def refine_made(prims, answers, made, observed, pushes, *, steps: int, jacobian: str,
                settings, prior=None, prior_weight=0.0):
  """One tower, one policy: each answer refined on the pushes made up to it.

  Args:
    prims: the prior's boxes (K) (their densities are not read).
    answers: (M, K) the loop's slots after 1..M pushes.
    made: (M,) the candidate pushes' indices, in the order made.
    observed: (N, T, 7) the true tower under every candidate push, whole trajectories.
    pushes: the N candidate pushes.
    steps, jacobian, settings: the refinement's (`RefineConfig`, a JAX engine).
    prior, prior_weight: None, or the MAP step's Gaussian prior on log densities
      (`refine.density_prior` of the prior model's scores) and its weight (may be traced):
      what holds a box the pushes made barely move at what its look says.

  Returns:
    (M, K) slots: refined where the fit came closer over those pushes, else the answer's;
    and (M,) whether it did.
  """
  slots, closer = [], []
  for k in range(1, answers.shape[0] + 1):  # static: k pushes make shapes (k, T, 7)
    r, kept = refine_on(prims, answers[k - 1], made[:k], observed, pushes, steps=steps,
                        jacobian=jacobian, settings=settings, prior=prior,
                        prior_weight=prior_weight)
    slots.append(kept)
    closer.append(r.closer)
  return jnp.stack(slots), jnp.stack(closer)
