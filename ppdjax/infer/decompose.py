"""`make_decompose_fn`: networks, density sampling, physics and refinement in one `jax.jit`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from ppdjax.conventions import NUM_DENSITY_SLOTS, OBS_KEYS, VOXEL_RESOLUTION
from ppdjax.dataset.camera import check_camera
from ppdjax.infer.depth_fit import check_depth
from ppdjax.infer.image_fit import check_image
from ppdjax.infer.fit import fit_boxes
from ppdjax.infer.refine import check_jacobian, density_prior, refine_if_closer
from ppdjax.infer import faces, sampling
from ppdjax.nn.estimator import combine_logits
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes, default_pushes
from ppdjax.sim.rollout_mjx import Settings, settings_for
from ppdjax.training import checkpoints
from ppdjax.training import estimator as estimator_module


# The screen `make_decompose_fn` uses with the depth fit (experiments/results/screen_study)
SCREEN_STEPS_WITH_DEPTH = 32
# the default screen runs only where it keeps at most this fraction of the candidates:
# with fewer (e.g. the demo's 128 samples, 64 kept) it simulates almost as many steps and
# compiles a second rollout (about 20 s of tracing and 40 s of compiling on a 2-core CPU)
SCREEN_MIN_RATIO = 4


@struct.dataclass
class Decomposition:
  """What `decompose` returns for a batch of B objects (K boxes, P pushes, T steps).

  Attributes:
    primitives: Primitives (B, K): the boxes (fitted to the voxels with `fit`, else the
      network's) with the selected (and refined) densities; `valid` marks the boxes.
    density_logits: (B, K, 100) the density scores per box that sampling and refinement
      used: the network's, or with an estimator its log-probabilities and the network's
      combined (`ppdjax.nn.estimator.combine_logits`).
    score: (B,) trajectory distance (metres) of the returned densities.
    scores: (B, S) every sampled candidate's distance (candidate 0: the arg-max; inf for
      one screened out, `make_decompose_fn(screen_steps=)`).
    trajectories: (B, P, T, 7) the returned object simulated under the pushes.
  """

  primitives: Primitives
  density_logits: jax.Array
  score: jax.Array
  scores: jax.Array
  trajectories: jax.Array


def check_observation(obs: dict, config) -> bool:
  """Raises ValueError naming a wrong key, shape, dtype or value; True if batched.

  The image must be uint8 RGB (0..255), as datasets store it: a float image in [0, 1]
  would reach the network scaled 255 times too small, so it is refused, not guessed at.
  """
  missing = [k for k in OBS_KEYS if k not in obs]
  if missing:
    raise ValueError(f"observation lacks {missing}; expected {', '.join(OBS_KEYS)}")
  traj = obs["trajectories"]
  p = config.model.num_pushes
  batched = np.ndim(traj) == 4
  lead = (np.shape(traj)[0],) if batched else ()
  expected = {"trajectories": lead + (p, None, 7), "voxels": lead + (VOXEL_RESOLUTION,) * 3,
              "image": lead + (None, None, 3)}
  for name, shape in expected.items():
    got = np.shape(obs[name])
    if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
      want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
      raise ValueError(f"observation[{name!r}]: expected shape {want}, got {got}")
  if not isinstance(traj, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(traj))):
    raise ValueError("observation['trajectories'] contains NaN or inf")
  image = obs["image"]
  image_dtype = image.dtype if hasattr(image, "dtype") else np.asarray(image).dtype
  if image_dtype != np.uint8:
    raise ValueError(f"observation['image']: expected uint8 RGB in 0..255, got {image_dtype} "
                     "(for a float image in [0, 1]: (image * 255).round().astype(np.uint8))")
  voxels = obs["voxels"]
  if not isinstance(voxels, jax.core.Tracer):
    v = np.asarray(voxels)
    if not (np.issubdtype(v.dtype, np.number) or v.dtype == bool) or np.any((v != 0) & (v != 1)):
      raise ValueError("observation['voxels']: expected a 0/1 occupancy grid")
  return batched


def is_paper_pushes(pushes: Pushes) -> bool:
  """Whether `pushes` are the paper's four (`default_pushes()`), values and all."""
  paper = default_pushes()
  return (not pushes.is_strike and pushes.num == paper.num
          and pushes.duration == paper.duration
          and all(np.allclose(a, b) for a, b in zip(pushes.arrays()[:3], paper.arrays()[:3])))


def default_screen_steps(fit_with: tuple[str, ...], num_samples: int, screen_keep: int) -> int:
  """`make_decompose_fn`'s screen when none is given: SCREEN_STEPS_WITH_DEPTH with the
  depth fit and at least SCREEN_MIN_RATIO × `screen_keep` candidates, else 0 (a screen
  keeping a quarter or more saves little and compiles a second rollout)."""
  return (SCREEN_STEPS_WITH_DEPTH if "depth" in fit_with
          and num_samples >= SCREEN_MIN_RATIO * screen_keep else 0)


def make_decompose_fn(trained, *, num_samples: int = 512, fit: bool = True,
                      camera: dict | None = None, fit_with: tuple[str, ...] | None = None,
                      refine: bool = False,
                      refine_steps: int = 12, prior_weight: float = 0.0,
                      mass_match: bool = False, screen_steps: int | None = None,
                      screen_keep: int = 64, face_spread: float = 0.0,
                      selection_horizon: int = 0, refine_prior: float = 0.0,
                      refine_jacobian: str = "forward",
                      estimator=None,
                      estimator_weight: float = 1.0, pushes: Pushes | None = None,
                      settings: Settings | None = None):
  """One jitted `decompose(observation, key) -> Decomposition` for a trained model.

  Args:
    trained: a training workdir, or the (model, config) pair `ppdjax.load` returns.
    num_samples: density candidates per object (1: the network's arg-max only).
    fit: replace the network's boxes by boxes fitted to the voxels (`ppdjax.fit_boxes`,
      started from the network's); the network's k-th density scores go to the k-th
      fitted box from the bottom. False: the network's boxes, as the paper.
    camera: the images' camera (`open_dataset(DIR).camera`), for the observations the
      fit reads beside the voxels (`fit_with`). Needs `fit`.
    fit_with: which observations the fit reads beside the voxels: any of "image" (faces
      moved within half a voxel onto the image's edges: the paper's inputs) and "depth"
      (then refined against observation["depth"]: faces the camera sees become
      sub-voxel), through `fit_boxes(..., image=, depth=, camera=)`. None: ("depth",)
      with a camera, () without. Needs the camera.
    refine: fit the densities by Levenberg–Marquardt through MJX, from the candidate
      closest in trajectory (whatever `prior_weight` selects: that start refines best,
      docs/inference.md); the fit replaces the selection only where its trajectory
      distance is below every candidate's.
    refine_steps: LM iterations.
    prior_weight: τ of `select_densities` (0: the closest trajectory wins).
    mass_match: `select_densities`' second pass: candidates scaled to the closest one's
      total mass and simulated again (twice the rollouts; continuous densities).
    screen_steps: > 0 simulates every candidate over its first `screen_steps` steps only
      and the `screen_keep` closest over that prefix whole; the answer is the best of those
      (`select_densities`; 0: every candidate whole, the paper's). Candidates screened
      out have score inf. None: 32 with the depth fit and at least 4 × `screen_keep`
      candidates (on depth-fitted boxes the screen of 32 steps to 64 survivors kept the
      exhaustive answer for 98.8 % of 2,400 test towers, at 3.8× the objects/s in batches
      of 64 at 512 samples), else 0 (on coarser boxes it keeps it less
      often: docs/inference.md, "Screened selection").
    screen_keep: survivors of the screen per object.
    selection_horizon: > 0 picks the candidate closest over the first this many steps
      (`select_densities`; 0: all steps, the paper's). The paper preset's evaluation uses 32
      (`config.eval.selection_horizon`: chosen on the validation split, docs/inference.md);
      the reported score and refinement's start stay whole-trajectory.
    face_spread: > 0 (voxels; needs `fit`) draws each candidate's faces too, within this of
      the fitted ones (`faces.spread_faces`; 0.5: wherever the voxels allow them), and
      returns the winner's boxes: its trajectories come closer, its densities do not
      (docs/inference.md, "Faces drawn with the densities"). 0: the fitted boxes.
    refine_prior: > 0 makes refinement a MAP step under the network's density scores
      (`refine.refine_densities`'s prior_weight; 1e-5: a one-σ move costs about 3 mm of
      trajectory residual); 0 is plain least squares.
    refine_jacobian: "forward" (forward mode, K tangents), "differences" or "central"
      (K + 1 or 2K + 1 rollouts in one call: where the rollouts run as the box-plane GPU
      kernel, 3x faster and slightly less accurate; docs/inference.md).
    estimator: a density estimator (its folder, or the model `training.estimator.load`
      returns) that reads the fitted boxes and the trajectories; its log-probabilities,
      times `estimator_weight`, join the network's for sampling and the MAP prior. Needs
      `fit` and the paper's pushes.
    estimator_weight: see `estimator`.
    pushes: the pushes the observations were recorded with (None: those of the model's
      training data, `generation.pushes_of(config.data)`: the paper's four for towers).
    settings: the engine the observations were simulated with: MjxSettings or
      BoxPlaneSettings; None: the default settings of the engine that made the model's
      training data (`config.data.backend`, `rollout_mjx.settings_for`).

  Returns:
    decompose(observation, key): observation is a dict with "voxels" (32,32,32),
    "image" (H,W,3) uint8 and "trajectories" (P,T,7) (and "depth" (H',W') metres with a
    camera), or a batch of them (leading B); the result has the same leading axes.
  """
  if isinstance(trained, str):
    trained = checkpoints.load(trained)
  model, config = trained
  if num_samples < 1:
    raise ValueError(f"num_samples must be >= 1, got {num_samples}")
  if fit_with is None:
    fit_with = ("depth",) if camera is not None else ()
  fit_with = tuple(fit_with)
  if set(fit_with) - {"image", "depth"}:
    raise ValueError(f"fit_with: expected any of ('image', 'depth'), got {fit_with}")
  if fit_with and camera is None:
    raise ValueError(f"fit_with={fit_with} needs the images' camera (camera=)")
  if screen_steps is None:
    screen_steps = default_screen_steps(fit_with, num_samples, screen_keep)
  sampling.check_screen(screen_steps, screen_keep, num_samples, 0)  # its errors, now
  sampling.check_selection_horizon(selection_horizon)
  if camera is not None and not fit:
    raise ValueError("camera is for the image and depth fits: it needs fit=True")
  faces.check_spread(face_spread, fit)
  if camera is not None:
    camera = check_camera(camera)
  keys = OBS_KEYS + (("depth",) if "depth" in fit_with else ())
  if estimator is not None and not fit:
    raise ValueError("the estimator reads fitted boxes: it needs fit=True")
  if pushes is None:
    from ppdjax.dataset.generation import pushes_of  # pylint: disable=import-outside-toplevel
    pushes = pushes_of(config.data)
  if estimator is not None and not is_paper_pushes(pushes):
    raise ValueError("the estimator was trained on the paper's four pushes; these pushes "
                     "(given, or the model's training data's) are others")
  if isinstance(estimator, str):
    estimator = estimator_module.load(estimator)[0]
  if settings is None:
    settings = settings_for(config.data.get("backend", "mjx"))
  check_jacobian(refine_jacobian)  # its error, now
  graphdef, state = nnx.split(model)
  est_graphdef, est_state = nnx.split(estimator) if estimator is not None else (None, None)

  @jax.jit
  def run(state, est_state, obs, key):
    model = nnx.merge(graphdef, state)
    prims, raw = model.decode(obs)
    k = prims.num_slots
    logits = raw.density_logits[:, :k, :NUM_DENSITY_SLOTS]
    traj = obs["trajectories"].astype(jnp.float32)
    if fit:
      prims = fit_boxes(obs["voxels"], init=prims,
                        image=obs["image"] if "image" in fit_with else None,
                        depth=obs.get("depth"),
                        camera=camera if fit_with else None).replace(density=prims.density)
    if est_graphdef is not None:
      logits = combine_logits(logits, nnx.merge(est_graphdef, est_state)(prims, traj),
                              estimator_weight)
    keys = jax.random.split(key, traj.shape[0])
    sel = jax.vmap(lambda p, l, o, kk: sampling.select_densities(
        p, l, o, pushes, num_samples=num_samples, key=kk, prior_weight=prior_weight,
        mass_match=mass_match, screen_steps=screen_steps, screen_keep=screen_keep,
        face_spread=face_spread, selection_horizon=selection_horizon,
        settings=settings))(prims, logits, traj, keys)
    pick = lambda index: jax.tree.map(  # each object's candidate `index` (B,)
        lambda x: jnp.take_along_axis(x, index.reshape((-1,) + (1,) * (x.ndim - 1)), 1)[:, 0],
        sel.boxes)
    prims = pick(sel.best).replace(density=sel.density)
    score, sim = sel.score, sel.trajectories  # no second rollout: latency is per rollout
    # from the candidate closest over all steps whatever τ and the horizon chose, as the
    # evaluation's +Refine; where refinement is not closer, +Sample's answer stays (the
    # evaluation's row keeps the start: the same answer at τ = 0 and selection_horizon = 0)
    if refine:
      start = pick(jnp.argmin(sel.scores, -1))
      ref = jax.vmap(lambda p, lg, o, d: refine_if_closer(
          p, o, d, pushes, steps=refine_steps,
          prior=density_prior(lg) if refine_prior > 0 else None, prior_weight=refine_prior,
          jacobian=refine_jacobian, settings=settings))(start, logits, traj, sel.scores.min(-1))
      # kept where it is closer than every candidate; else the +Sample answer stays
      prims = jax.tree.map(  # the refined boxes (the closest candidate's) with their densities
          lambda r, p: jnp.where(ref.closer.reshape((-1,) + (1,) * (p.ndim - 1)), r, p),
          ref.primitives, prims)
      score = jnp.where(ref.closer, ref.distance, score)
      sim = jnp.where(ref.closer[:, None, None, None], ref.trajectories, sim)
    return Decomposition(prims, logits, score, sel.scores, sim)

  def decompose(observation: dict, key: jax.Array) -> Decomposition:
    batched = check_observation(observation, config)
    lead = np.shape(observation["voxels"])[:1] if batched else ()
    if "depth" in fit_with:
      if "depth" not in observation:
        raise ValueError("observation lacks 'depth', which the fit asks for (fit_with)")
      check_depth(observation["depth"], camera, lead)  # shape, finite, > 0
    if "image" in fit_with:
      check_image(observation["image"], camera, lead)  # shape and the camera's size
    obs = {k: jnp.asarray(observation[k]) for k in keys}
    if not batched:
      obs = jax.tree.map(lambda x: x[None], obs)
    out = run(state, est_state, obs, key)
    return out if batched else jax.tree.map(lambda x: x[0], out)

  return decompose
