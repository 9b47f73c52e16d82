"""+Joint: box faces and densities fitted together to the motion, the depth image and a prior.

+Refine fits densities on fixed boxes, so a face a few millimetres off is paid for by a
wrong density. `refine_joint` moves both: Levenberg–Marquardt over the 6K faces (as
`depth_fit`, offsets along each box's axes, touching faces tied) and the K log densities,
on one residual vector

  [ trajectory residual (`metrics.pose_residual`, every push and step, metres);
    depth_weight · depth residual (`depth.residuals`, arctan-robust as in `depth_fit`);
    TIE_WEIGHT · gaps of touching faces;
    sqrt(prior_weight · n) · z, z = (log ρ − mean) / std under the density prior ]

with faces kept within `bound` of the start (half a voxel: where the voxels allow them,
once the start is the voxel or depth fit) and densities within the slot range. The
Jacobian of all 7K parameters comes from `jax.jacfwd` through the MJX rollout and the ray
cast: one batched forward pass per iteration. As `refine_densities`, the iterations fit
a growing horizon (`refine.horizon_schedule`), and a step is kept only if it lowers the
cost.

Measured so far (docs/inference.md): from boxes a few millimetres off their true faces,
with the depth image rendered from the true boxes, it recovers faces and densities
exactly (tests/test_joint.py). From a depth fit's start on fresh towers (with the
fit's sweep) it does worse than +Refine (48 % of boxes within 5 % of their density
against 60 %): the faces' tail grows, because the depth residual left on edge pixels
(rays grazing an edge) outweighs the trajectory residual near the truth by ~10⁴
(experiments/results/joint_study.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ppdjax import metrics
from ppdjax.conventions import MAX_DENSITY, MIN_DENSITY
from ppdjax.dataset.depth import camera_rays
from ppdjax.infer import depth as depth_lib
from ppdjax.infer.depth_fit import (MIN_HALF, ROBUST, TIE_WEIGHT, VOXEL, boxes_from_faces,
                                    touching_faces)
from ppdjax.infer.refine import density_prior, horizon_schedule
from ppdjax.primitives import Primitives, bottom_to_top, quat_to_mat
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, Settings, simulate


@struct.dataclass
class JointFit:
  """`refine_joint`'s answer for one object.

  Attributes:
    primitives: the fitted boxes and densities (the start where the fit did not lower the
      cost).
    cost_start, cost: the cost (0.5·|residual|² over the whole trajectory, with depth and
      prior terms) before and after.
    accepted: iterations that lowered the cost.
    trajectories: (P, T, 7) the returned object simulated.
  """

  primitives: Primitives
  cost_start: jax.Array
  cost: jax.Array
  accepted: jax.Array
  trajectories: jax.Array


def refine_joint(prims: Primitives, observed: jax.Array, pushes: Pushes | None = None, *,
                 depth=None, intrinsics=None, camera_from_world=None,
                 prior: tuple | None = None, prior_weight: float = 0.0,
                 depth_weight: float = 1.0, bound: float = VOXEL / 2, steps: int = 12,
                 warmup_steps: int = 8, damping: float = 1e-3,
                 settings: Settings = DEFAULT_SETTINGS) -> JointFit:
  """Fits one object's faces and densities to its motion (and depth image).

  Args:
    prims: one object (K boxes): the start, e.g. depth-fitted boxes with the best
      sample's densities.
    observed: (P, T, 7) observed trajectories.
    pushes: the P pushes (None: the paper's four).
    depth: (H, W) observed depth (metres along the optical axis) or None (motion only).
    intrinsics, camera_from_world: the depth image's camera (with `depth`).
    prior: (mean (K,), std (K,)) Gaussian prior on log densities (`refine.density_prior`).
    prior_weight: the prior's weight per residual entry, as `refine_densities`'s.
    depth_weight: weight of the depth residual beside the trajectory's (both metres).
    bound: how far (m) a face may move from the start.
    steps: LM iterations, each one forward-mode rollout with 7K tangents.
    warmup_steps: the first horizon of `refine.horizon_schedule`.
    damping: the starting LM damping.
    settings: the engine's settings (the observations'; MJX or box-plane).
  """
  pushes = default_pushes() if pushes is None else pushes
  t = observed.shape[-2]
  k = prims.valid.shape[0]
  valid = prims.valid
  ties = touching_faces(prims)
  rot = quat_to_mat(prims.quat)
  centre_axes = jnp.einsum("kji,kj->ki", rot, prims.pos)
  faces0 = jnp.concatenate([-prims.half_size, prims.half_size], -1)
  u0 = jnp.log(jnp.clip(prims.density, MIN_DENSITY, MAX_DENSITY))
  x0 = jnp.concatenate([faces0.reshape(-1), u0])
  mean, std = (jnp.zeros(k), jnp.ones(k)) if prior is None else prior
  prior_w = 0.0 if prior is None else prior_weight
  if depth is not None:
    h, w = depth.shape
    origin, dirs = camera_rays(intrinsics, camera_from_world, h, w)
    obs_depth = jnp.asarray(depth, jnp.float32).reshape(-1)
    mask = depth_lib.mask_from_rays(obs_depth, origin, dirs, camera_from_world)
    dirs = dirs.reshape(-1, 3)

  def unpack(x):
    faces, u = x[:6 * k].reshape(k, 6), x[6 * k:]
    boxes = boxes_from_faces(prims, faces)
    keep = valid[:, None]
    boxes = boxes.replace(half_size=jnp.where(keep, boxes.half_size, prims.half_size),
                          pos=jnp.where(keep, boxes.pos, prims.pos),
                          density=jnp.where(valid, jnp.exp(u), prims.density))
    return faces, u, boxes

  n_traj = observed.shape[0] * t * 6

  def residual(x):  # (entries,): trajectory, ties, depth, prior z; aux: the rollout
    faces, u, boxes = unpack(x)
    sim = simulate(boxes, pushes, steps=t, settings=settings)
    hi, lo = centre_axes + faces[:, 3:], centre_axes + faces[:, :3]
    parts = [metrics.pose_residual(sim, observed).reshape(-1),
             TIE_WEIGHT * jnp.where(ties, hi[:, None, :] - lo[None, :, :], 0.0).reshape(-1)]
    if depth is not None:
      pix = depth_lib.residuals(boxes, obs_depth, mask, origin, dirs)
      parts.append(depth_weight * ROBUST * jnp.arctan(pix / ROBUST))
    parts.append(jnp.where(valid, (u - mean) / std, 0.0))
    return jnp.concatenate(parts), sim

  def with_aux(x):
    r, sim = residual(x)
    return r, (r, sim)

  def scale(horizon, size):
    """(entries,) per-entry weights at a horizon: trajectory steps past it count 0, the
    prior sqrt(prior_weight · trajectory entries within it)."""
    steps_in = (jnp.arange(t) < horizon)[None, :, None]
    traj = jnp.broadcast_to(steps_in, (observed.shape[0], t, 6)).reshape(-1)
    n = observed.shape[0] * 6 * jnp.minimum(horizon, t)
    return jnp.concatenate([traj.astype(jnp.float32), jnp.ones(size - n_traj - k),
                            jnp.full(k, jnp.sqrt(prior_w * n))])

  def cost(r, horizon):
    return 0.5 * jnp.sum((scale(horizon, r.size) * r) ** 2)

  def project(x):
    faces = jnp.clip(x[:6 * k].reshape(k, 6), faces0 - bound, faces0 + bound)
    lo = jnp.minimum(faces[:, :3], faces[:, 3:] - 2 * MIN_HALF)
    u = jnp.where(valid, jnp.clip(x[6 * k:], jnp.log(MIN_DENSITY), jnp.log(MAX_DENSITY)), u0)
    return jnp.concatenate([jnp.concatenate([lo, faces[:, 3:]], -1).reshape(-1), u])

  free = jnp.concatenate([jnp.repeat(valid, 6), valid])

  def iterate(carry, horizons):
    """Evaluates the last proposal with its Jacobian (one forward-mode rollout), keeps it
    if it lowered the cost at the horizon it was proposed for, proposes the next step."""
    proposed_with, horizon = horizons
    trial, x, r, jac, sim, lam, accepted, r0, sim0 = carry
    jac_t, (r_t, sim_t) = jax.jacfwd(with_aux, has_aux=True)(trial)
    first = jnp.isinf(lam)
    c_t = cost(r_t, proposed_with)
    take = first | (jnp.isfinite(c_t) & (c_t < cost(r, proposed_with)))
    x, r, jac, sim = jax.tree.map(lambda a, b: jnp.where(take, a, b),
                                  (trial, r_t, jac_t, sim_t), (x, r, jac, sim))
    lam = jnp.where(first, damping, jnp.where(take, lam * 0.3, lam * 4.0))
    r0, sim0 = jnp.where(first, r_t, r0), jnp.where(first, sim_t, sim0)
    sc = scale(horizon, r.size)
    jac_h = jnp.where(free, sc[:, None] * jac, 0.0)
    jtj, g = jac_h.T @ jac_h, jac_h.T @ (sc * r)
    a = jtj + jnp.diag(lam * jnp.where(free, jnp.diagonal(jtj), 0.0) + 1e-9 + (~free))
    proposal = project(x - jnp.where(free, jnp.linalg.solve(a, g), 0.0))
    return (proposal, x, r, jac, sim, lam, accepted + (take & ~first), r0, sim0), None

  horizon = horizon_schedule(steps, warmup_steps, t)
  horizons = (jnp.concatenate([horizon[:1], horizon[:-1]]), horizon)
  r_size = jax.eval_shape(lambda y: residual(y)[0], x0).shape[0]
  p = observed.shape[0]
  zeros_sim = jnp.zeros((p, t, 7))
  init = (x0, x0, jnp.zeros(r_size), jnp.zeros((r_size, x0.size)), zeros_sim,
          jnp.float32(jnp.inf), 0, jnp.zeros(r_size), zeros_sim)
  (_, x, r, _, sim, _, accepted, r0, sim0), _ = jax.lax.scan(iterate, init, horizons)
  # the warm-up passes fit a shorter horizon: never return what is worse on the whole
  c0, c1 = cost(r0, t), cost(r, t)
  better = c1 < c0
  _, _, boxes = unpack(jnp.where(better, x, x0))
  return JointFit(boxes, c0, jnp.minimum(c0, c1), accepted, jnp.where(better, sim, sim0))


def joint_batch(prims, logits, obs_traj, depth, true, mags, *, steps, prior_weight, camera, pushes,
                settings, at_once: int = 8):
  """`refine_joint` over a batch (B, K) from the closest samples, as the evaluation runs it:
  the prior from each object's slot logits (when prior_weight > 0), the depth image with
  `camera` (else motion only; `depth` is then ignored), each object's push magnitudes `mags`
  (B, P), `at_once` objects at a time; returns the
  densities, trajectory MAE (mm), costs and face errors against `true` (bottom to top)."""
  def one(p, lg, traj, d, m):
    prior = density_prior(lg) if prior_weight > 0 else None
    kw = ({} if camera is None else
          {"depth": d, "intrinsics": jnp.asarray(camera["intrinsics"], jnp.float32),
           "camera_from_world": jnp.asarray(camera["camera_from_world"], jnp.float32)})
    j = refine_joint(p, traj, pushes.replace(magnitudes=m), prior=prior,
                     prior_weight=prior_weight, steps=steps, settings=settings, **kw)
    return j.primitives, metrics.trajectory_mae(j.trajectories, traj), j.cost_start, j.cost
  with jax.default_matmul_precision("highest"):  # the ray cast, as depth_fit
    boxes, mae, c0, c1 = jax.lax.map(lambda a: one(*a), (prims, logits, obs_traj, depth, mags),
                                     batch_size=at_once)
  return {"density": boxes.density, "mae": mae, "cost_start": c0, "cost": c1,
          "faces": metrics.face_errors(bottom_to_top(boxes), true)}
