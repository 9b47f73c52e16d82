"""Decomposition with physics in the loop: density sampling through MJX and refinement.

The network proposes boxes and, per box, a distribution over the 100 density slots.
`select_densities` draws joint density assignments from it, simulates each under the
pushes and keeps the one whose trajectories are closest to the observation (paper
Sec. 4.3, "+Sample"). `refine_densities` then treats the densities as continuous and fits
them by Levenberg–Marquardt with Jacobians from forward-mode differentiation through MJX.
`make_decompose_fn` puts encoders, generator, sampling, simulation and refinement in one
`jax.jit`. Distances and units: `ppdjax.metrics` (pose residual in metres, rotations at
0.5 m per radian).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from ppdjax import metrics
from ppdjax.materials import NUM_DENSITY_SLOTS, SLOT_DENSITY
from ppdjax.physics import Pushes, default_pushes
from ppdjax.primitives import Primitives
from ppdjax.rollout_mjx import DEFAULT_SETTINGS, MjxSettings, rollout_object

MIN_DENSITY = SLOT_DENSITY  # kg/m^3: slot 0
MAX_DENSITY = NUM_DENSITY_SLOTS * SLOT_DENSITY  # slot 99


@struct.dataclass
class Selection:
  """What sampling found for one object (S candidates, K boxes).

  Attributes:
    density: (K,) kg/m^3 of the best candidate.
    score: trajectory distance of the best candidate (metres, `metrics.trajectory_distance`).
    scores: (S,) every candidate's distance, in draw order (candidate 0 is the most likely).
    slots: (S, K) the candidates' density slots (0 for padded boxes).
    distinct: (S,) False for a candidate that repeats an earlier one (small supports).
    mae: (S,) every candidate's trajectory MAE (mm, `metrics.trajectory_mae`).
    trajectories: (P, T, 7) the best candidate simulated under the pushes.
  """

  density: jax.Array
  score: jax.Array
  scores: jax.Array
  slots: jax.Array
  distinct: jax.Array
  mae: jax.Array
  trajectories: jax.Array


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
  # Lexicographic sort by slots (3 per int32 code), then draw index: the first of each run
  # of equal assignments is the earliest drawn.
  codes = [sum(draws[:, j] * 100 ** (j - c) for j in range(c, min(c + 3, k)))
           for c in range(0, k, 3)]
  index = jnp.arange(m)
  order = jnp.lexsort([index] + codes[::-1])
  sorted_codes = jnp.stack([c[order] for c in codes], -1)
  repeat = jnp.concatenate([jnp.zeros(1, bool),
                            jnp.all(sorted_codes[1:] == sorted_codes[:-1], -1)])
  duplicate = jnp.zeros(m, bool).at[order].set(repeat)
  take = jnp.argsort(jnp.where(duplicate, m + index, index))[:num_samples]
  return draws[take], ~duplicate[take]


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
  return out.replace(density=(slots + 1.0) * SLOT_DENSITY)


def score_candidates(candidates: Primitives, observed_PTx7: jax.Array, pushes: Pushes,
                     settings: MjxSettings = DEFAULT_SETTINGS, *,
                     keep_trajectories: bool = False):
  """(distance (S,), MAE (S,)[, trajectories (S, P, T, 7)]) of candidates (S, K)."""
  steps = observed_PTx7.shape[-2]

  def one(p):
    sim = rollout_object(p, pushes, steps=steps, settings=settings)
    scores = (metrics.trajectory_distance(sim, observed_PTx7),
              metrics.trajectory_mae(sim, observed_PTx7))
    return scores + (sim,) if keep_trajectories else scores
  return jax.vmap(one)(candidates)


def select_densities(prims: Primitives, density_logits: jax.Array, observed: jax.Array,
                     pushes: Pushes | None = None, *, num_samples: int, key: jax.Array,
                     include_mode: bool = True, prior_weight: float = 0.0,
                     settings: MjxSettings = DEFAULT_SETTINGS) -> Selection:
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
    settings: MJX solver settings (those the dataset was simulated with).

  Returns:
    Selection: best densities, its score and every candidate's score and MAE.
  """
  pushes = default_pushes() if pushes is None else pushes
  slots, distinct = candidate_slots(density_logits[:, :NUM_DENSITY_SLOTS], prims.valid,
                                    num_samples, key, include_mode=include_mode)
  scores, mae, sims = score_candidates(with_slots(prims, slots), observed, pushes, settings,
                                       keep_trajectories=True)
  best = jnp.argmin(scores - prior_weight * log_prior(density_logits, slots, prims.valid))
  return Selection(density=(slots[best] + 1.0) * SLOT_DENSITY, score=scores[best],
                   scores=scores, slots=slots, distinct=distinct, mae=mae,
                   trajectories=sims[best])


def refine_densities(prims: Primitives, observed: jax.Array, pushes: Pushes | None = None, *,
                     steps: int = 12, warmup_steps: int = 64, damping: float = 1e-3,
                     settings: MjxSettings = DEFAULT_SETTINGS) -> tuple[Primitives, dict]:
  """Fits the densities of valid boxes to the observed trajectories (Levenberg–Marquardt).

  Parameters are log densities, bounded to [100, 10,000] kg/m^3 (the slot range). The
  residual is `metrics.pose_residual` over all pushes; its Jacobian comes from
  `jax.jacfwd` through the MJX rollout (K tangents; reverse mode would have to go
  through the solver's loops). The first half of the iterations fit only the first
  `warmup_steps` steps, where the motion is smooth in the densities; the second half
  fit the whole trajectory, whose late part (after boxes land on edges) is informative
  but rugged. A step is kept only if it lowers the squared residual at the current
  horizon.

  Args:
    prims: one object (K boxes) with the starting densities (e.g. the best sample's).
    observed: (P, T, 7) observed trajectories.
    pushes: the P pushes (None: the paper's four).
    steps: LM iterations (each: one primal + K tangent rollouts, and one trial rollout).
    warmup_steps: the horizon of the first steps // 2 iterations.
    damping: initial λ of (JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr.
    settings: MJX solver settings.

  Returns:
    (Primitives with refined densities, {"cost_start", "cost": 0.5·|r|² over the whole
    trajectory before and after, "accepted": iterations that lowered the cost}). If the
    iterations end with a higher whole-trajectory cost, the start is returned.
  """
  pushes = default_pushes() if pushes is None else pushes
  t = observed.shape[-2]
  lo, hi = jnp.log(MIN_DENSITY), jnp.log(MAX_DENSITY)
  valid = prims.valid

  def residual(u, horizon):
    p = prims.replace(density=jnp.exp(u))
    r = metrics.pose_residual(rollout_object(p, pushes, steps=t, settings=settings), observed)
    return jnp.where(jnp.arange(t)[:, None] < horizon, r, 0.0).reshape(-1)

  def cost(r):
    return 0.5 * jnp.sum(r * r)

  def iterate(carry, horizon):
    u, lam, accepted = carry
    jac, r = jax.jacfwd(lambda v: (residual(v, horizon),) * 2, has_aux=True)(u)
    jac = jnp.where(valid, jac, 0.0)
    h, g = jac.T @ jac, jac.T @ r
    diag = jnp.where(valid, jnp.diagonal(h), 1.0)
    a = h + jnp.diag(lam * diag + 1e-9 + (~valid))
    trial = jnp.where(valid, jnp.clip(u - jnp.linalg.solve(a, g), lo, hi), u)
    c_trial = cost(residual(trial, horizon))
    better = jnp.isfinite(c_trial) & (c_trial < cost(r))
    return (jnp.where(better, trial, u), jnp.where(better, lam * 0.3, lam * 4.0),
            accepted + better), None

  horizons = jnp.where(jnp.arange(steps) < steps // 2, min(warmup_steps, t), t)
  u0 = jnp.log(jnp.clip(prims.density, MIN_DENSITY, MAX_DENSITY))
  (u, _, accepted), _ = jax.lax.scan(iterate, (u0, jnp.float32(damping), 0), horizons)
  # The warm-up iterations fit a shorter horizon and may raise the full-trajectory cost:
  # never return something worse than the start.
  c0, c1 = cost(residual(u0, t)), cost(residual(u, t))
  u = jnp.where(c1 < c0, u, u0)
  out = prims.replace(density=jnp.where(valid, jnp.exp(u), prims.density))
  return out, {"cost_start": c0, "cost": jnp.minimum(c1, c0), "accepted": accepted}


@struct.dataclass
class Decomposition:
  """What `decompose` returns for a batch of B objects (K boxes, P pushes, T steps).

  Attributes:
    primitives: Primitives (B, K): predicted geometry with the selected (and refined)
      densities; `valid` marks the boxes the generator emitted.
    density_logits: (B, K, 100) the network's density scores per box.
    score: (B,) trajectory distance (metres) of the returned densities.
    scores: (B, S) every sampled candidate's distance (candidate 0: the arg-max).
    trajectories: (B, P, T, 7) the returned object simulated under the pushes.
  """

  primitives: Primitives
  density_logits: jax.Array
  score: jax.Array
  scores: jax.Array
  trajectories: jax.Array


def check_observation(obs: dict, config) -> bool:
  """Raises ValueError naming a wrong key, shape or non-finite value; True if batched."""
  missing = [k for k in ("voxels", "image", "trajectories") if k not in obs]
  if missing:
    raise ValueError(f"observation lacks {missing}; expected voxels, image, trajectories")
  traj = obs["trajectories"]
  p = config.model.num_pushes
  batched = np.ndim(traj) == 4
  lead = (np.shape(traj)[0],) if batched else ()
  expected = {"trajectories": lead + (p, None, 7), "voxels": lead + (32, 32, 32),
              "image": lead + (None, None, 3)}
  for name, shape in expected.items():
    got = np.shape(obs[name])
    if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
      want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
      raise ValueError(f"observation[{name!r}]: expected shape {want}, got {got}")
  if not isinstance(traj, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(traj))):
    raise ValueError("observation['trajectories'] contains NaN or inf")
  return batched


def make_decompose_fn(trained, *, num_samples: int = 512, refine: bool = False,
                      refine_steps: int = 12, prior_weight: float = 0.0,
                      pushes: Pushes | None = None,
                      settings: MjxSettings = DEFAULT_SETTINGS):
  """One jitted `decompose(observation, key) -> Decomposition` for a trained model.

  Args:
    trained: a training workdir, or the (model, config) pair `ppdjax.load` returns.
    num_samples: density candidates per object (1: the network's arg-max only).
    refine: fit the best candidate's densities by Levenberg–Marquardt through MJX.
    refine_steps: LM iterations.
    prior_weight: τ of `select_densities` (0: the closest trajectory wins).
    pushes: the pushes the observations were recorded with (None: the paper's four).
    settings: MJX settings the observations were simulated with (the dataset's).

  Returns:
    decompose(observation, key): observation is a dict with "voxels" (32,32,32),
    "image" (H,W,3) uint8 and "trajectories" (P,T,7), or a batch of them (leading B);
    the result has the same leading axes.
  """
  if isinstance(trained, str):
    from ppdjax import checkpoints
    trained = checkpoints.load(trained)
  model, config = trained
  if num_samples < 1:
    raise ValueError(f"num_samples must be >= 1, got {num_samples}")
  pushes = default_pushes() if pushes is None else pushes
  graphdef, state = nnx.split(model)

  @jax.jit
  def run(state, obs, key):
    model = nnx.merge(graphdef, state)
    prims, raw = model.decode(obs)
    k = prims.num_slots
    logits = raw.density_logits[:, :k, :NUM_DENSITY_SLOTS]
    traj = obs["trajectories"].astype(jnp.float32)
    keys = jax.random.split(key, traj.shape[0])
    sel = jax.vmap(lambda p, l, o, kk: select_densities(
        p, l, o, pushes, num_samples=num_samples, key=kk, prior_weight=prior_weight,
        settings=settings))(
            prims, logits, traj, keys)
    prims = prims.replace(density=sel.density)
    score, sim = sel.score, sel.trajectories  # no second rollout: latency is per rollout
    if refine:
      refined, _ = jax.vmap(lambda p, o: refine_densities(p, o, pushes, steps=refine_steps,
                                                          settings=settings))(prims, traj)
      steps = traj.shape[-2]
      r_sim = jax.vmap(lambda p: rollout_object(p, pushes, steps=steps, settings=settings))(
          refined)
      r_score = metrics.trajectory_distance(r_sim, traj)
      better = r_score < score  # LM lowers the squared residual; keep it if the distance agrees
      pick = lambda a, b: jnp.where(better.reshape(better.shape + (1,) * (a.ndim - 1)), a, b)
      prims = jax.tree.map(pick, refined, prims)
      sim, score = pick(r_sim, sim), jnp.minimum(r_score, score)
    return Decomposition(prims, logits, score, sel.scores, sim)

  def decompose(observation: dict, key: jax.Array) -> Decomposition:
    batched = check_observation(observation, config)
    obs = {k: jnp.asarray(observation[k]) for k in ("voxels", "image", "trajectories")}
    if not batched:
      obs = jax.tree.map(lambda x: x[None], obs)
    out = run(state, obs, key)
    return out if batched else jax.tree.map(lambda x: x[0], out)

  return decompose
