"""+Refine: densities fitted by Levenberg–Marquardt with Jacobians through MJX (forward mode).

`refine_densities` treats the best sample's densities as continuous and fits them to the
observed trajectories; `refine_if_closer` keeps the fit only where it also lowers the
trajectory distance that +Sample ranks by (the one rule `decompose` and evaluation share).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ppdjax import metrics
from ppdjax.conventions import MAX_DENSITY, MIN_DENSITY
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, MjxSettings
from ppdjax.sim.simulate import simulate


def refine_densities(prims: Primitives, observed: jax.Array, pushes: Pushes | None = None, *,
                     steps: int = 12, warmup_steps: int = 64, damping: float = 1e-3,
                     settings: MjxSettings = DEFAULT_SETTINGS) -> tuple[Primitives, dict]:
  """Fits the densities of valid boxes to the observed trajectories (Levenberg–Marquardt).

  Parameters are log densities, bounded to [100, 10,000] kg/m^3 (the slot range). The
  residual is `metrics.pose_residual` over all pushes; its Jacobian comes from
  `jax.jacfwd` through the MJX rollout (K tangents in one forward pass; forward mode
  suits a handful of densities, docs/physics.md). The first half of the iterations fit
  only the first `warmup_steps` steps, where the motion is smooth in the densities; the second half
  fit the whole trajectory, whose late part (after boxes land on edges) is informative
  but rugged. A step is kept only if it lowers the squared residual at the current
  horizon.

  Args:
    prims: one object (K boxes) with the starting densities (e.g. the best sample's).
    observed: (P, T, 7) observed trajectories.
    pushes: the P pushes (None: the paper's four).
    steps: LM iterations (steps + 1 rollouts in all, each with its K tangents).
    warmup_steps: the horizon of the first steps // 2 iterations.
    damping: initial λ of (JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr.
    settings: MJX solver settings.

  Returns:
    (Primitives with refined densities, {"cost_start", "cost": 0.5·|r|² over the whole
    trajectory before and after, "accepted": iterations that lowered the cost,
    "trajectories": (P, T, 7) the returned densities simulated}). If the iterations end
    with a higher whole-trajectory cost, the start is returned.
  """
  pushes = default_pushes() if pushes is None else pushes
  t = observed.shape[-2]
  lo, hi = jnp.log(MIN_DENSITY), jnp.log(MAX_DENSITY)
  valid = prims.valid

  def residual(u):  # (P, T, 6) and, as aux, the same and the rollout
    sim = simulate(prims.replace(density=jnp.exp(u)), pushes, steps=t, settings=settings)
    r = metrics.pose_residual(sim, observed)
    return r, (r, sim)

  def cost(r, horizon):
    return 0.5 * jnp.sum(jnp.where(jnp.arange(t)[:, None] < horizon, r, 0.0) ** 2)

  def propose(u, r, jac, lam, horizon):
    keep = (jnp.arange(t) < horizon)[None, :, None]
    jac = jnp.where(keep[..., None] & valid, jac, 0.0).reshape(-1, valid.shape[0])
    r = jnp.where(keep, r, 0.0).reshape(-1)
    h, g = jac.T @ jac, jac.T @ r
    diag = jnp.where(valid, jnp.diagonal(h), 1.0)
    a = h + jnp.diag(lam * diag + 1e-9 + (~valid))
    return jnp.where(valid, jnp.clip(u - jnp.linalg.solve(a, g), lo, hi), u)

  # Each pass evaluates the last proposal and its Jacobian in ONE forward-mode rollout
  # (the Jacobian at an accepted point is the next one's), keeps it if it lowered the cost
  # at the horizon it was proposed for, and proposes the next step. Pass 0 evaluates the
  # start; passes 1..steps the proposals of passes 0..steps-1.
  def iterate(carry, horizons):
    proposed_with, horizon = horizons
    trial, u, r, jac, sim, lam, accepted, r0, sim0 = carry
    jac_t, (r_t, sim_t) = jax.jacfwd(residual, has_aux=True)(trial)
    first = jnp.isinf(lam)  # pass 0: nothing to compare with
    c_t = cost(r_t, proposed_with)
    take = first | (jnp.isfinite(c_t) & (c_t < cost(r, proposed_with)))
    u, r, jac, sim = jax.tree.map(lambda a, b: jnp.where(take, a, b), (trial, r_t, jac_t, sim_t),
                                  (u, r, jac, sim))
    lam = jnp.where(first, damping, jnp.where(take, lam * 0.3, lam * 4.0))
    r0, sim0 = jnp.where(first, r_t, r0), jnp.where(first, sim_t, sim0)
    carry = (propose(u, r, jac, lam, horizon), u, r, jac, sim, lam,
             accepted + (take & ~first), r0, sim0)
    return carry, None

  horizon = jnp.where(jnp.arange(steps + 1) < steps // 2, min(warmup_steps, t), t)
  horizons = (jnp.concatenate([horizon[:1], horizon[:-1]]), horizon)
  u0 = jnp.log(jnp.clip(prims.density, MIN_DENSITY, MAX_DENSITY))
  p, n, k = pushes.num, t, valid.shape[0]
  zeros_r, zeros_sim = jnp.zeros((p, n, 6)), jnp.zeros((p, n, 7))
  init = (u0, u0, zeros_r, jnp.zeros((p, n, 6, k)), zeros_sim, jnp.float32(jnp.inf), 0,
          zeros_r, zeros_sim)
  (_, u, r, _, sim, _, accepted, r0, sim0), _ = jax.lax.scan(iterate, init, horizons)
  # The warm-up passes fit a shorter horizon and may raise the full-trajectory cost:
  # never return something worse than the start.
  c0, c1 = cost(r0, t), cost(r, t)
  better = c1 < c0
  u = jnp.where(better, u, u0)
  out = prims.replace(density=jnp.where(valid, jnp.exp(u), prims.density))
  return out, {"cost_start": c0, "cost": jnp.minimum(c1, c0), "accepted": accepted,
               "trajectories": jnp.where(better, sim, sim0)}


@struct.dataclass
class Refinement:
  """`refine_if_closer`'s answer for one object.

  Attributes:
    primitives: the refined densities where they are closer, else the start's.
    distance: trajectory distance (m) of what `primitives` holds.
    trajectories: (P, T, 7) the refined object simulated (whether kept or not).
    closer: whether the refined densities were kept.
    cost_start, cost: 0.5·|r|² before and after the LM iterations.
  """

  primitives: Primitives
  distance: jax.Array
  trajectories: jax.Array
  closer: jax.Array
  cost_start: jax.Array
  cost: jax.Array


def refine_if_closer(prims: Primitives, observed: jax.Array, distance: jax.Array,
                     pushes: Pushes | None = None, *, steps: int = 12,
                     settings: MjxSettings = DEFAULT_SETTINGS) -> Refinement:
  """Refines one object's densities; keeps them only if the trajectory distance drops.

  LM lowers the squared pose residual; +Sample ranks by the mean residual norm
  (`metrics.trajectory_distance`). The refined densities replace the start only where
  that distance agrees.

  Args:
    prims: one object with the starting densities (the best sample's).
    observed: (P, T, 7).
    distance: the start's trajectory distance (metres), as +Sample computed it.
    pushes, steps, settings: as `refine_densities`.
  """
  pushes = default_pushes() if pushes is None else pushes
  refined, info = refine_densities(prims, observed, pushes, steps=steps, settings=settings)
  sim = info["trajectories"]
  new = metrics.trajectory_distance(sim, observed)
  closer = new < distance
  kept = jax.tree.map(lambda a, b: jnp.where(closer, a, b), refined, prims)
  return Refinement(kept, jnp.minimum(new, distance), sim, closer, info["cost_start"],
                    info["cost"])
