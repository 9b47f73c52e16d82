"""Pushes chosen on the refined answer: A-optimal design under its Laplace posterior.

The gain over the candidates (`ppdjax.infer.active`, the `active` policy) weighs the
+Sample posterior, whose candidates refinement has left behind. These loops (`designNN`)
choose on the refined answer instead: the Gauss-Newton information JᵀJ / σ² of each
candidate push about the boxes' log densities (J by forward differences through the
simulator over the push's first NN steps, σ² the refined answer's residual per entry on
the pushes made) and the push that leaves the least expected squared slot error (a slot is
100 kg/m³, so a box's log-density variance costs ρ² / 100² slots²). How they compare
with the gain over the candidates: the README's sixth run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax import metrics
from ppdjax.conventions import SLOT_DENSITY
from ppdjax.infer.refine import DIFFERENCE_STEP
from ppdjax.sim.rollout_mjx import simulate

try:  # run as a script (its folder on the path) or imported by the tests (as a package)
  import refine_loop
except ImportError:
  from active_pushes import refine_loop


def push_information(prims, pushes, *, steps: int, settings,
                     step: float = DIFFERENCE_STEP) -> tuple[jax.Array, jax.Array]:
  """What each push tells about one object's log densities at its current densities.

  Returns (info (N, steps, K, K): the information JᵀJ of push n's pose residual over its
  first t + 1 steps, cumulated over t, so that `info[:, h - 1]` is that of the first h; the
  object simulated under the N pushes (N, steps, 7)). J from forward differences of `step`
  in log density: K + 1 rollouts of every push in one batched call. Padded boxes tell
  nothing."""
  k = prims.density.shape[-1]
  log_rho = (jnp.log(jnp.where(prims.valid, prims.density, 1.0))[None]
             + jnp.concatenate([jnp.zeros((1, k)), step * jnp.eye(k)]))
  points = jax.tree.map(lambda a: jnp.broadcast_to(a, (k + 1,) + jnp.shape(a)), prims)
  sims = simulate(points.replace(density=jnp.where(prims.valid, jnp.exp(log_rho),
                                                   prims.density)),
                  pushes, steps=steps, settings=settings)  # (K + 1, N, T, 7)
  jac = metrics.pose_residual(sims[1:], sims[:1]) / step  # (K, N, T, 6)
  jac = jnp.where(prims.valid[:, None, None, None], jac, 0.0)
  with jax.default_matmul_precision("highest"):  # TF32 products read noise (infer/refine.py)
    per_step = jnp.einsum("kntc,lntc->ntkl", jac, jac)
  return jnp.cumsum(per_step, axis=1), sims[0]


def expected_slot_error(info_NxKxK, made_N, density_K, valid_K, noise_var,
                        prior_std: float = 1.0) -> jax.Array:
  """(N,) the expected squared slot error summed over the boxes once push n joins the
  pushes made (`made_N`): the Laplace posterior's log-density variances
  diag(((Σ_made F + F_n) / σ² + I / prior_std²)⁻¹) times (ρ / 100 kg/m³)². F: the pushes'
  information at one horizon; σ² (`noise_var`) per residual entry; `prior_std`, a broad
  Gaussian on each log density, only bounds what no push tells."""
  k = density_K.shape[-1]
  made_info = jnp.sum(jnp.where(made_N[:, None, None], info_NxKxK, 0.0), 0)
  both = valid_K[:, None] & valid_K[None, :]
  precision = (jnp.where(both, made_info[None] + info_NxKxK, 0.0) / noise_var
               + jnp.eye(k) / prior_std ** 2)
  # symmetric positive definite: P⁻¹ = L⁻ᵀL⁻¹ by Cholesky, so each variance is a sum of
  # squares (never negative), accurate where the information spans many orders of magnitude
  with jax.default_matmul_precision("highest"):
    lower = jnp.linalg.cholesky(precision)
    inverse = jax.scipy.linalg.solve_triangular(
        lower, jnp.broadcast_to(jnp.eye(k), precision.shape), lower=True)
    variance = jnp.sum(inverse ** 2, axis=-2)  # (N, K): column sums of L⁻¹ squared
  weight = jnp.where(valid_K, (density_K / SLOT_DENSITY) ** 2, 0.0)
  return jnp.sum(weight * variance, -1)


def design_loop(prims, slots, distinct, distances, observed, pushes, first, *, pushes_made: int,
                horizon: int, steps: int, jacobian: str, settings):
  """One tower: each next push the one of least `expected_slot_error` at the refined answer.

  After each push: the closest candidate over the pushes made (`slots` (S, K), `distinct`
  (S,), `distances` (S, N) over the selection's horizon, as `run.closed_loop`), refined on
  the whole trajectories of those pushes (`refine_loop.refine_on`); then every candidate
  push's information about the refined densities over its first `horizon` steps, the noise
  variance from the refined answer's residual on the pushes made over the same steps, and
  the next push among those not yet made. The first push is `first`.

  Returns {"answer": (M, K) the closest candidates, "refined_answer": (M, K) refined where
  closer, "refined_closer": (M,), "pushes": (M,)}.
  """
  done = jnp.zeros(distances.shape[1], bool)
  made, answers, refined, closer = [first], [], [], []
  for k in range(pushes_made):  # static: k + 1 pushes make shapes (k + 1, T, 7)
    done = done.at[made[-1]].set(True)
    d = jnp.sum(jnp.where(done, distances, 0.0), -1) / jnp.sum(done)
    answers.append(slots[jnp.argmin(jnp.where(distinct, d, jnp.inf))])
    r, kept = refine_loop.refine_on(prims, answers[-1], jnp.stack(made), observed, pushes,
                                    steps=steps, jacobian=jacobian, settings=settings)
    refined.append(kept)
    closer.append(r.closer)
    if k + 1 == pushes_made:
      break
    at = r.primitives
    info, sim = push_information(at, pushes, steps=horizon, settings=settings)
    residual = metrics.pose_residual(sim, observed[:, :horizon])  # (N, h, 6)
    entries = jnp.sum(done) * horizon * residual.shape[-1]
    noise_var = jnp.maximum(jnp.sum(jnp.where(done[:, None, None], residual ** 2, 0.0))
                            / entries, 1e-8)  # at least (0.1 mm)² per entry
    error = expected_slot_error(info[:, horizon - 1], done, at.density, at.valid, noise_var)
    # a push whose rollout is not finite (or a residual that is not) is never chosen; if
    # none is finite, the first push not made yet
    error = jnp.where(done | ~jnp.isfinite(error), jnp.inf, error)
    made.append(jnp.where(jnp.isfinite(jnp.min(error)), jnp.argmin(error), jnp.argmin(done)))
  return {"answer": jnp.stack(answers), "refined_answer": jnp.stack(refined),
          "refined_closer": jnp.stack(closer), "pushes": jnp.stack(made)}
