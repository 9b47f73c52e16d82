"""+Refine: densities fitted by Levenberg–Marquardt with Jacobians through the simulator.

`refine_densities` treats a sample's densities (the closest one's, in the evaluation and
`decompose`) as continuous and fits them to the observed trajectories; `refine_if_closer`
keeps the fit only where it also lowers the trajectory distance that +Sample ranks by (the
one rule `decompose` and evaluation share).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax import metrics
from ppdjax.conventions import (MAX_DENSITY, MIN_DENSITY, NUM_DENSITY_SLOTS,
                                slot_to_density_jax)
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, Settings, simulate

JACOBIANS = ("forward", "differences", "central")
DIFFERENCE_STEP = 1e-3  # the differences' step in log density (0.1 % of a density)
# With `inertia`, each box's inertia scale (its inertia over a uniform box's of the same
# mass) is fitted within these bounds: a shell around an empty core reaches about 1.45 and
# a heavy core in a light shell about 0.75 (`dataset.hollow`), with room beyond either.
INERTIA_SCALE_RANGE = (0.5, 2.0)


def check_jacobian(jacobian: str) -> str:
  """`jacobian` if it names a way to take +Refine's Jacobian (JACOBIANS), else ValueError.
  "forward": `jax.jacfwd`, K tangents through the XLA step (the default). "differences"
  and "central": `difference_jacobian`, K + 1 or 2K + 1 plain rollouts in one call, which
  the box-plane GPU kernel runs (it has no derivatives of its own): 3x faster on an H100,
  slightly less accurate (docs/inference.md)."""
  if jacobian not in JACOBIANS:
    raise ValueError(f"jacobian must be one of {JACOBIANS}, got {jacobian!r}")
  return jacobian


def difference_jacobian(residual, u: jax.Array, step: float = DIFFERENCE_STEP,
                        central: bool = False):
  """`jax.jacfwd(residual, has_aux=True)(u)`'s contract by finite differences: the K + 1
  points u, u + step·e_k (forward differences), or the 2K + 1 points u, u ± step·e_k
  (`central`), simulated in one batched call (`jax.vmap`: one kernel launch).
  residual(u) -> (r (...), aux); returns (dr/du (..., K), aux at u)."""
  k = u.shape[-1]
  shifts = [jnp.zeros((1, k)), step * jnp.eye(k)] + ([-step * jnp.eye(k)] if central else [])
  r, aux = jax.vmap(residual)(u[None] + jnp.concatenate(shifts))
  if central:
    jac = (r[1:k + 1] - r[k + 1:]) / (2 * step)  # (K, ...)
  else:
    jac = (r[1:] - r[:1]) / step
  return jnp.moveaxis(jac, 0, -1), jax.tree.map(lambda a: a[0], aux)


def horizon_schedule(steps: int, warmup_steps: int, t: int) -> np.ndarray:
  """(steps + 1,) how many trajectory steps each LM pass fits (`refine_densities`,
  `joint.refine_joint`): a continuation. The first half of the passes fit horizons that
  double from `warmup_steps` (8, 16, 32, ... below t), shared evenly; the rest fit the
  whole trajectory. Over a short horizon the motion is smooth in the densities; each
  doubling starts where the last one ended, so the late, rugged part of the motion (boxes
  landing on edges) is fitted only from close by. Measured on true boxes 30 % off
  (docs/inference.md): a single switch 64 → 256 leaves 38 % of boxes within 5 %; the
  doubling from 8, at the same 12 passes, 100 %."""
  passes = steps + 1
  stages = []
  h = max(1, min(warmup_steps, t))
  while h < t:
    stages.append(h)
    h *= 2
  first = passes - (passes + 1) // 2 if stages else 0
  out = [stage for i, stage in enumerate(stages)
         for _ in range(first // len(stages) + (i < first % len(stages)))]
  return np.asarray(out + [t] * (passes - len(out)), np.int32)


def density_prior(logits_Kx100: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(mean (K,), std (K,)) of log density under the network's per-box slot distribution:
  the Gaussian that +Refine's MAP step uses as its prior (std at least 0.05)."""
  p = jax.nn.softmax(logits_Kx100[..., :NUM_DENSITY_SLOTS], -1)
  log_rho = jnp.log(slot_to_density_jax(jnp.arange(NUM_DENSITY_SLOTS)))
  mean = (p * log_rho).sum(-1)
  std = jnp.sqrt((p * (log_rho - mean[..., None]) ** 2).sum(-1))
  return mean, jnp.maximum(std, 0.05)


def refine_densities(prims: Primitives, observed: jax.Array, pushes: Pushes | None = None, *,
                     steps: int = 12, warmup_steps: int = 8, damping: float = 1e-3,
                     prior: tuple | None = None, prior_weight: float = 0.0,
                     horizons=None, jacobian: str = "forward",
                     difference_step: float = DIFFERENCE_STEP, inertia: bool = False,
                     settings: Settings = DEFAULT_SETTINGS) -> tuple[Primitives, dict]:
  """Fits the densities of valid boxes to the observed trajectories (Levenberg–Marquardt).

  Parameters are log densities, bounded to [100, 10,000] kg/m^3 (the slot range). The
  residual is `metrics.pose_residual` over all pushes; its Jacobian comes from
  `jax.jacfwd` through the rollout (K tangents in one forward pass; forward mode suits a
  handful of densities, docs/physics.md) or from finite differences (K + 1 rollouts in
  one batched call; `check_jacobian`). The iterations fit a horizon that
  grows (`horizon_schedule`: doubling from `warmup_steps` over the first half, then the
  whole trajectory, whose late part after boxes land on edges is informative but
  rugged). A step is kept only if it lowers the cost at the horizon it was proposed for.

  Args:
    prims: one object (K boxes) with the starting densities (e.g. the best sample's).
    observed: (P, T, 7) observed trajectories.
    pushes: the P pushes (None: the paper's four).
    steps: LM iterations (steps + 1 rollouts in all, each with its K tangents).
    warmup_steps: the first horizon of `horizon_schedule`.
    damping: initial λ of (JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr.
    prior: (mean (K,), std (K,)) of a Gaussian prior on log densities (`density_prior` of
      the network's logits), or None.
    prior_weight: with a prior, the MAP cost is 0.5·|r|² + 0.5·prior_weight·n·Σ z_k²,
      z_k = (log ρ_k − mean_k) / std_k and n the number of residual entries at the
      horizon: a one-σ move costs as much as sqrt(prior_weight) metres of residual on every
      entry (1e-5: about 3 mm). 0 is a plain least-squares fit.
    horizons: (steps + 1,) the trajectory steps each pass fits, instead of
      `horizon_schedule(steps, warmup_steps, T)` (e.g. another continuation to compare).
    jacobian: "forward" (`jax.jacfwd`), "differences" or "central" (forward or central
      `difference_jacobian`; the fast choice where the rollouts run as the GPU kernel).
    difference_step: the differences' step in log density.
    inertia: also fit each valid box's inertia scale (`Primitives.inertia_scale`, a
      hollow or filled block's mass distribution; 2K unknowns, the scales' logarithms
      within INERTIA_SCALE_RANGE and under no prior), starting from the given scales (1
      where None); the returned boxes then carry them (1 on padded slots). The Jacobian
      then takes 2K tangents, or 2K + 1 (4K + 1 central) rollouts.
    settings: the engine's settings (MjxSettings or BoxPlaneSettings).

  Returns:
    (Primitives with refined densities, {"cost_start", "cost": 0.5·|r|² over the whole
    trajectory before and after, "accepted": iterations that lowered the cost,
    "trajectories": (P, T, 7) the returned densities simulated}). If the iterations end
    with a higher whole-trajectory cost, the start is returned.
  """
  pushes = default_pushes() if pushes is None else pushes
  method = check_jacobian(jacobian)
  t = observed.shape[-2]
  k = prims.valid.shape[0]
  # the unknowns u: K log densities, then (inertia) K log inertia scales
  start_scale = with_inertia_scale(prims).inertia_scale
  box_bounds = [(MIN_DENSITY, MAX_DENSITY)] + ([INERTIA_SCALE_RANGE] if inertia else [])
  lo, hi = (jnp.repeat(jnp.log(jnp.asarray(b, jnp.float32)), k) for b in zip(*box_bounds))
  valid = jnp.tile(prims.valid, len(box_bounds))
  on_prior = valid & (jnp.arange(valid.shape[0]) < k)  # the prior is on the densities alone

  def with_unknowns(u):
    dens = jnp.exp(u[:k])
    if not inertia:
      return prims.replace(density=dens)
    return prims.replace(density=dens, inertia_scale=jnp.where(prims.valid, jnp.exp(u[k:]), 1.0))

  def residual(u):  # (P, T, 6) and, as aux, the same and the rollout
    sim = simulate(with_unknowns(u), pushes, steps=t, settings=settings)
    r = metrics.pose_residual(sim, observed)
    return r, (r, sim)

  mean, std = (jnp.zeros(k), jnp.ones(k)) if prior is None else prior
  weight_per_entry = 0.0 if prior is None else prior_weight
  if inertia:
    mean, std = jnp.concatenate([mean, jnp.zeros(k)]), jnp.concatenate([std, jnp.ones(k)])
  entries_per_step = observed.shape[0] * 6  # P pushes x 6 residual components

  def prior_terms(u, horizon):  # (weight w, z): cost 0.5·w·Σ z², gradient w·z/std
    w = weight_per_entry * entries_per_step * jnp.minimum(horizon, t)
    return w, jnp.where(on_prior, (u - mean) / std, 0.0)

  def cost(r, horizon, u):
    w, z = prior_terms(u, horizon)
    return (0.5 * jnp.sum(jnp.where(jnp.arange(t)[:, None] < horizon, r, 0.0) ** 2)
            + 0.5 * w * jnp.sum(z * z))

  def propose(u, r, jac, lam, horizon):
    keep = (jnp.arange(t) < horizon)[None, :, None]
    jac = jnp.where(keep[..., None] & valid, jac, 0.0).reshape(-1, valid.shape[0])
    r = jnp.where(keep, r, 0.0).reshape(-1)
    w, z = prior_terms(u, horizon)
    h = jac.T @ jac + jnp.diag(jnp.where(on_prior, w / std ** 2, 0.0))
    g = jac.T @ r + jnp.where(on_prior, w * z / std, 0.0)
    diag = jnp.where(valid, jnp.diagonal(h), 1.0)
    a = h + jnp.diag(lam * diag + 1e-9 + (~valid))
    return jnp.where(valid, jnp.clip(u - jnp.linalg.solve(a, g), lo, hi), u)

  # Each pass evaluates the last proposal and its Jacobian in ONE batched call
  # (the Jacobian at an accepted point is the next one's), keeps it if it lowered the cost
  # at the horizon it was proposed for, and proposes the next step. Pass 0 evaluates the
  # start; passes 1..steps the proposals of passes 0..steps-1.
  def iterate(carry, horizons):
    proposed_with, horizon = horizons
    trial, u, r, jac, sim, lam, accepted, r0, sim0 = carry
    if method == "forward":
      jac_t, (r_t, sim_t) = jax.jacfwd(residual, has_aux=True)(trial)
    else:
      jac_t, (r_t, sim_t) = difference_jacobian(residual, trial, difference_step,
                                                central=method == "central")
    first = jnp.isinf(lam)  # pass 0: nothing to compare with
    c_t = cost(r_t, proposed_with, trial)
    take = first | (jnp.isfinite(c_t) & (c_t < cost(r, proposed_with, u)))
    u, r, jac, sim = jax.tree.map(lambda a, b: jnp.where(take, a, b), (trial, r_t, jac_t, sim_t),
                                  (u, r, jac, sim))
    lam = jnp.where(first, damping, jnp.where(take, lam * 0.3, lam * 4.0))
    r0, sim0 = jnp.where(first, r_t, r0), jnp.where(first, sim_t, sim0)
    carry = (propose(u, r, jac, lam, horizon), u, r, jac, sim, lam,
             accepted + (take & ~first), r0, sim0)
    return carry, None

  horizon = (horizon_schedule(steps, warmup_steps, t) if horizons is None
             else np.asarray(horizons, np.int32))
  if horizon.shape != (steps + 1,):
    raise ValueError(f"horizons must give each of the {steps + 1} passes a horizon, got "
                     f"shape {horizon.shape}")
  horizons = (jnp.concatenate([horizon[:1], horizon[:-1]]), horizon)
  u0 = jnp.clip(jnp.log(jnp.concatenate(
      [prims.density] + ([start_scale] if inertia else [])).astype(jnp.float32)), lo, hi)
  p, n = pushes.num, t
  zeros_r, zeros_sim = jnp.zeros((p, n, 6)), jnp.zeros((p, n, 7))
  init = (u0, u0, zeros_r, jnp.zeros((p, n, 6, len(u0))), zeros_sim, jnp.float32(jnp.inf), 0,
          zeros_r, zeros_sim)
  # Full float32 products: GPUs default to TF32 (10-bit mantissas) for float32 matmuls,
  # and whether XLA takes that path depends on the batch's shapes. The normal equations
  # and differences then read noise, and the fit depended on what else shared the call
  # (experiments/active_pushes/README.md, "Fourth look").
  with jax.default_matmul_precision("highest"):
    (_, u, r, _, sim, _, accepted, r0, sim0), _ = jax.lax.scan(iterate, init, horizons)
  # The warm-up passes fit a shorter horizon and may raise the full-trajectory cost:
  # never return something worse than the start.
  c0, c1 = cost(r0, t, u0), cost(r, t, u)
  better = c1 < c0
  u = jnp.where(better, u, u0)
  out = with_unknowns(u)
  out = out.replace(density=jnp.where(prims.valid, out.density, prims.density))
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
                     prior: tuple | None = None, prior_weight: float = 0.0,
                     jacobian: str = "forward", inertia: bool = False,
                     settings: Settings = DEFAULT_SETTINGS) -> Refinement:
  """Refines one object's densities; keeps them only if the trajectory distance drops.

  LM lowers the squared pose residual (with a prior: the MAP cost); +Sample ranks by the
  mean residual norm (`metrics.trajectory_distance`). The refined densities replace the
  start only where that distance agrees (without a prior) or where the MAP cost fell
  (with one, whatever its weight: a MAP step may trade a little distance for a likelier
  density).

  Args:
    prims: one object with the starting densities (the closest sample's).
    observed: (P, T, 7).
    distance: the start's trajectory distance (metres), as +Sample computed it.
    pushes, steps, prior, prior_weight, jacobian, inertia, settings: as
      `refine_densities` (with `inertia`, the answer carries inertia scales, 1 where the
      start is kept and had none).
  """
  pushes = default_pushes() if pushes is None else pushes
  if inertia:  # the start's boxes carry scales as the refined ones will
    prims = with_inertia_scale(prims)
  refined, info = refine_densities(prims, observed, pushes, steps=steps, prior=prior,
                                   prior_weight=prior_weight, jacobian=jacobian,
                                   inertia=inertia, settings=settings)
  sim = info["trajectories"]
  new = metrics.trajectory_distance(sim, observed)
  closer = new < distance
  if prior is not None:  # the MAP step (prior_weight may be traced: one compile for all)
    closer = info["cost"] < info["cost_start"]
  kept = jax.tree.map(lambda a, b: jnp.where(closer, a, b), refined, prims)
  return Refinement(kept, jnp.where(closer, new, distance), sim, closer, info["cost_start"],
                    info["cost"])


def refine_from_candidates(boxes: Primitives, scores: jax.Array, distinct: jax.Array,
                           observed: jax.Array, pushes: Pushes, *, starts: int = 1,
                           **options) -> Refinement:
  """`refine_if_closer` from each of the `starts` distinct candidates closest by `scores`
  (one object's S candidates, `boxes` (S, K)); the refinement of least distance is
  returned, kept (`closer`) only where it is closer than every candidate. One start is
  `decompose`'s refinement from the closest; several, in one batched call, let the fit
  leave a basin the closest candidate sits in (measured on a CPU proxy of the look-alike
  towers: experiments/search_continuation). `options`: `refine_if_closer`'s; with several
  starts only least squares (no prior: a MAP step's costs would not compare)."""
  if starts > 1 and options.get("prior") is not None:
    raise ValueError("refine.starts > 1 compares the starts' distances: it runs without a "
                     "prior (refine.prior_weight 0)")
  scores = jnp.where(jnp.isnan(scores), jnp.inf, scores)  # a rollout that blew up: last
  order = jnp.argsort(jnp.where(distinct, scores, jnp.inf))[:starts]
  closest = jnp.min(scores)
  refs = jax.vmap(lambda i: refine_if_closer(jax.tree.map(lambda x: x[i], boxes), observed,
                                             closest, pushes, **options))(order)
  best = jnp.argmin(refs.distance)  # every start's distance, at most the closest's
  return jax.tree.map(lambda x: x[best], refs)


def with_inertia_scale(prims: Primitives) -> Primitives:
  """`prims` with inertia scales (1, a uniform box, where it has none)."""
  if prims.inertia_scale is not None:
    return prims
  return prims.replace(inertia_scale=jnp.ones(jnp.shape(prims.density), jnp.float32))


def refine_batch(prims, logits, obs_traj, sample_dist, sample_mae, mags, *, steps, prior_weight,
                 pushes, settings, jacobian="forward", inertia=False):
  """`refine_if_closer` over a batch (B, K), as the evaluation runs it: refined densities
  where kept, a MAP step under each object's slot logits when prior_weight > 0; returns
  the densities (with `inertia`, the inertia scales too), costs, distance and trajectory
  MAE (mm; the sample's where not kept).
  `mags` (B, P): each object's push magnitudes (`pushes.object_magnitudes`).
  `prior_weight` may also be (B,), one per object: then every object takes the MAP step
  (even at weight 0, accepted by its cost), and many weights share one compiled call."""
  use_prior = np.ndim(prior_weight) > 0 or prior_weight > 0
  weights = jnp.broadcast_to(jnp.asarray(prior_weight, jnp.float32), sample_dist.shape)

  def one(p, lg, traj, d0, m0, w, m):
    prior = density_prior(lg) if use_prior else None
    r = refine_if_closer(p, traj, d0, pushes.replace(magnitudes=m), steps=steps, prior=prior,
                         prior_weight=w, jacobian=jacobian, inertia=inertia, settings=settings)
    mae = jnp.where(r.closer, metrics.trajectory_mae(r.trajectories, traj), m0)
    return {"density": r.primitives.density, "cost_start": r.cost_start, "cost": r.cost,
            "dist": r.distance, "mae": mae, "closer": r.closer,
            **({"inertia_scale": r.primitives.inertia_scale} if inertia else {})}
  return jax.vmap(one)(prims, logits, obs_traj, sample_dist, sample_mae, weights, mags)
