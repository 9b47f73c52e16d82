"""`make_decompose_fn`: networks, density sampling, physics and refinement in one `jax.jit`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from ppdjax.conventions import (DEPTH_VIDEO, NUM_DENSITY_SLOTS, OBS_KEYS, PUSH_MAGNITUDES,
                                TIMESTEP, VOXEL_RESOLUTION)
from ppdjax.dataset.camera import camera_dict, check_camera
from ppdjax.infer.depth_fit import check_depth
from ppdjax.infer.image_fit import check_image
from ppdjax.infer.config import DecomposeConfig, FitConfig
from ppdjax.infer.fit import fit_boxes
from ppdjax.infer.refine import density_prior, refine_from_candidates, with_inertia_scale
from ppdjax.infer import posterior as posterior_module
from ppdjax.infer import sampling, search
from ppdjax.nn.estimator import combine_logits
from ppdjax.nn.model import physics_key
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import Pushes, check_magnitudes, default_pushes, object_magnitudes
from ppdjax.sim.rollout_mjx import Settings, engine_settings, jax_engine
from ppdjax.training import checkpoints
from ppdjax.training import estimator as estimator_module


MIN_STEPS = 30  # an observation's shortest trajectories: 0.1 s, before boxes land
MAX_TRAVEL = 100.0  # m: a pushed 1 m object observed farther than this is in another unit
QUAT_TOLERANCE = 1e-3  # |norm - 1| of an observed quaternion


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
      one screened out, `SelectConfig.screen_steps`; S: samples × rounds with +Search,
      `select.rounds`). With a selection horizon (`SelectConfig.horizon`), no refinement
      and no +Search, the distance over that horizon: the
      candidates are simulated that far only (the winner over every step).
    trajectories: (B, P, T, 7) the returned object simulated under the pushes.
    candidates: (B, S, K) int32, the candidates' density slots, in `scores`' order.
    distinct: (B, S) False for a candidate that repeats an earlier one (a small support;
      with `fit.face_spread` each has its own faces, so none repeats).
    posterior: each box's density posterior over the candidates (`DensityPosterior`
      (B, K): marginals, mean, interval, identified flag, correlation between boxes;
      `PosteriorConfig`). It reads the candidates, not the refined answer (and with
      `select.mass_match` the drawn slots at their mass-scaled distances).
  """

  primitives: Primitives
  density_logits: jax.Array
  score: jax.Array
  scores: jax.Array
  trajectories: jax.Array
  candidates: jax.Array
  distinct: jax.Array
  posterior: posterior_module.DensityPosterior


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
  if np.shape(traj)[-2] < MIN_STEPS:
    raise ValueError(f"observation['trajectories']: {np.shape(traj)[-2]} steps; at least "
                     f"{MIN_STEPS} (0.1 s at dt {TIMESTEP:.5f} s) are needed to tell densities "
                     f"apart (the model was trained on {config.data.steps})")
  if not isinstance(traj, jax.core.Tracer):
    t = np.asarray(traj)
    if not np.all(np.isfinite(t)):
      raise ValueError("observation['trajectories'] contains NaN or inf")
    far = np.abs(t[..., :3]).max()
    if far > MAX_TRAVEL:
      raise ValueError(f"observation['trajectories']: a position {far:.4g} m from the origin; "
                       f"objects are 1 m across and pushed ones stay within {MAX_TRAVEL:g} m "
                       "(positions in metres, object frame; were these millimetres?)")
    norm = np.linalg.norm(t[..., 3:], axis=-1)
    if np.any(np.abs(norm - 1.0) > QUAT_TOLERANCE):
      raise ValueError("observation['trajectories']: quaternions (columns 3:7, w x y z) must "
                       f"have unit norm; their norms range {norm.min():.4g}..{norm.max():.4g}")
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
  if physics_key(config.model) == DEPTH_VIDEO:
    check_depth_video(obs, lead + (p, config.model.video_frames, config.model.video_size,
                                   config.model.video_size))
  return batched


def check_depth_video(obs: dict, shape: tuple[int, ...]) -> None:
  """The RGB-D model's physics observation: (.., P, F, S, S) finite depths in metres."""
  if DEPTH_VIDEO not in obs:
    raise ValueError(f"observation lacks {DEPTH_VIDEO!r}: this model reads a depth video of "
                     f"each push, shape {shape} (pushes, frames, pixels; metres), "
                     "as ppdjax.dataset.depth_video.depth_videos renders it")
  got = np.shape(obs[DEPTH_VIDEO])
  if got != shape:
    raise ValueError(f"observation[{DEPTH_VIDEO!r}]: expected shape {shape}, got {got}")
  if not isinstance(obs[DEPTH_VIDEO], jax.core.Tracer):
    d = np.asarray(obs[DEPTH_VIDEO], np.float32)
    if not np.all(np.isfinite(d)) or d.min() <= 0:
      raise ValueError(f"observation[{DEPTH_VIDEO!r}]: depths must be finite and > 0 metres "
                       f"(no hit: far away, e.g. 100), got {d.min():.4g}..{d.max():.4g}")


def is_paper_pushes(pushes: Pushes) -> bool:
  """Whether `pushes` are the paper's four (`default_pushes()`), values and all."""
  paper = default_pushes()
  return (not pushes.is_strike and pushes.num == paper.num
          and pushes.duration == paper.duration
          and all(np.allclose(a, b) for a, b in zip(pushes.arrays()[:3], paper.arrays()[:3])))


def model_camera(trained) -> dict:
  """The camera of a model's training data: saved beside an exported or trained model
  (`checkpoints.DECOMPOSE_FILE`), else the datasets' camera at its image size."""
  if isinstance(trained, str):
    saved = checkpoints.read_decompose(trained)
    if saved is not None and saved.get("camera") is not None:
      return saved["camera"]
    trained = (None, checkpoints.read_config(trained))
  size = trained[1].data.image_size
  return camera_dict(size, size)


def model_settings(trained) -> DecomposeConfig:
  """The decomposition settings a model was evaluated with: its saved `eval` section (the
  one source; decompose.json shows them as a DecomposeConfig beside the camera)."""
  config = checkpoints.read_config(trained) if isinstance(trained, str) else trained[1]
  return DecomposeConfig.from_eval(config.eval)


def fit_stage(obs: dict, pred: Primitives, fit: FitConfig, camera) -> Primitives:
  """The boxes the densities go on, for a batch (B, K): `pred` (the network's) or, with
  `fit.enabled`, boxes fitted to the voxels from them (and to the image and depth as
  `fit` asks); the densities stay `pred`'s. The evaluation's fitted rows call it too."""
  if not fit.enabled:
    return pred
  return fit_boxes(obs["voxels"], init=pred, image=obs["image"] if fit.image else None,
                   depth=obs["depth"] if fit.depth else None,
                   camera=camera if fit.with_ else None).replace(density=pred.density)


def make_decompose_fn(model, config: DecomposeConfig | None = None, *,
                      camera: dict | None = None, pushes: Pushes | None = None,
                      engine: str | Settings | None = None):
  """One jitted `decompose(observation, key) -> Decomposition` for a trained model.

  Args:
    model: a training workdir or exported model (such as "assets/blocks_model"), or the
      (model, config) pair `ppdjax.load` returns.
    config: the settings (`DecomposeConfig`); None: the model's own, those its tables
      report (its saved `eval` section). `DecomposeConfig.paper()` and `.best()` are the
      presets; `config.replace(**{"select.samples": 128})` changes one setting.
    camera: the images' camera (`open_dataset(DIR).camera`), for a fit that reads the
      image or the depth; None: the camera of the model's training data.
    pushes: the pushes the observations were recorded with (None: those of the model's
      training data, the paper's four for towers).
    engine: the simulator the observations come from: "mjx", "box_plane" (or their
      `Settings`); None: the engine of the model's training data. Its JAX step refines,
      and simulates the candidates on an accelerator; on a CPU MuJoCo's C engine
      simulates them (`config.simulator`).

  Returns:
    decompose(observation, key): observation is a dict with "voxels" (32,32,32), "image"
    (H,W,3) uint8 and "trajectories" (P,T,7) (and "depth" (H',W') metres for a depth fit),
    or a batch of them (leading B); the result has the same leading axes.
  """
  path = model if isinstance(model, str) else None
  trained = checkpoints.load(model) if path is not None else model
  net, run_config = trained
  config = model_settings(path or trained) if config is None else config
  if not isinstance(config, DecomposeConfig):
    raise TypeError(f"config: expected a DecomposeConfig, got {type(config).__name__}")
  config.validate()
  fit, select, refine, belief = config.fit, config.select, config.refine, config.posterior
  if fit.with_:
    camera = check_camera(model_camera(path or trained) if camera is None else camera)
  elif camera is not None:
    raise ValueError("camera is for the image and depth fits: this config reads neither "
                     "(fit.image, fit.depth)")
  keys = (OBS_KEYS + (("depth",) if fit.depth else ())
          + ((DEPTH_VIDEO,) if physics_key(run_config.model) == DEPTH_VIDEO else ()))
  if pushes is None:
    from ppdjax.dataset.generation import pushes_of  # pylint: disable=import-outside-toplevel
    pushes = pushes_of(run_config.data)
  if not isinstance(pushes, Pushes):
    raise TypeError(f"pushes: expected ppdjax.Pushes, got {type(pushes).__name__}")
  pushes.validate()
  if config.estimator.path and not is_paper_pushes(pushes):
    raise ValueError("the estimator was trained on the paper's four pushes; these pushes "
                     "(given, or the model's training data's) are others")
  if pushes.num != run_config.model.num_pushes:
    raise ValueError(f"pushes: {pushes.num} given; the model reads "
                     f"{run_config.model.num_pushes} trajectories (its training data's pushes)")
  estimator = None
  if config.estimator.path:
    estimator = estimator_module.load(config.estimator.path)[0]
  if engine is None:
    engine = run_config.data.get("backend", "mjx")
  settings = engine_settings(config.simulator, engine)
  # refinement through the observations' own physics: C's small late departures from
  # the JAX step cost top-1 after refinement (experiments/cpu_engine)
  refine_settings = jax_engine(engine)
  graphdef, state = nnx.split(net)
  est_graphdef, est_state = nnx.split(estimator) if estimator is not None else (None, None)

  @jax.jit
  def run(state, est_state, obs, key):
    pred, raw = nnx.merge(graphdef, state).decode(obs)
    logits = raw.density_logits[:, :pred.num_slots, :NUM_DENSITY_SLOTS]
    traj = obs["trajectories"].astype(jnp.float32)
    mags = object_magnitudes(pushes, obs, traj.shape[0])  # (B, P): each object's pushes
    prims = fit_stage(obs, pred, fit, camera)
    if est_graphdef is not None:
      logits = combine_logits(logits, nnx.merge(est_graphdef, est_state)(prims, traj),
                              config.estimator.weight)
    if select.searches:
      draw = lambda p, l, o, kk, m: search.search_densities(  # noqa: E731
          p, l, o, pushes.replace(magnitudes=m), num_samples=select.samples,
          rounds=select.rounds, key=kk, inertia=select.inertia,
          prior_weight=select.tau(fit.enabled), selection_horizon=select.horizon,
          continuation=select.continuation, settings=settings)
    else:
      draw = lambda p, l, o, kk, m: sampling.select_densities(  # noqa: E731
          p, l, o, pushes.replace(magnitudes=m), num_samples=select.samples, key=kk,
          prior_weight=select.tau(fit.enabled), mass_match=select.mass_match,
          screen_steps=select.screen_steps, screen_keep=select.screen_keep,
          face_spread=fit.face_spread, selection_horizon=select.horizon,
          whole_scores=refine.enabled, settings=settings)
    sel = jax.vmap(draw)(prims, logits, traj, object_keys(key, traj.shape[0]), mags)
    distinct = sel.distinct | (fit.face_spread > 0)
    post = jax.vmap(lambda s, d, l, v, u: posterior_module.density_posterior(
        s, d, sampling.log_prior(l, s, v), v, scale=belief.scale, level=belief.level,
        identified_width=belief.identified_width, distinct_S=u,
        prior_power=belief.prior_power))(
            sel.slots, sel.scores, logits, prims.valid, distinct)
    pick = lambda index: jax.tree.map(  # each object's candidate `index` (B,)
        lambda x: jnp.take_along_axis(x, index.reshape((-1,) + (1,) * (x.ndim - 1)), 1)[:, 0],
        sel.boxes)
    prims = pick(sel.best).replace(density=sel.density)
    score, sim = sel.score, sel.trajectories  # no second rollout: latency is per rollout
    if refine.enabled:  # from the candidates closest over all steps, whatever selected
      ref = jax.vmap(lambda b, s, u, lg, o, m: refine_from_candidates(
          b, s, u, o, pushes.replace(magnitudes=m), starts=refine.starts, steps=refine.steps,
          prior=density_prior(lg) if refine.prior_weight > 0 else None,
          prior_weight=refine.prior_weight, jacobian=refine.jacobian, inertia=refine.inertia,
          settings=refine_settings))(sel.boxes, sel.scores, distinct, logits, traj, mags)
      if refine.inertia and not select.inertia:  # +Sample's answer: uniform boxes
        prims = with_inertia_scale(prims)
      # kept where it is closer than every candidate; else the +Sample answer stays
      prims = jax.tree.map(
          lambda r, p: jnp.where(ref.closer.reshape((-1,) + (1,) * (p.ndim - 1)), r, p),
          ref.primitives, prims)
      score = jnp.where(ref.closer, ref.distance, score)
      sim = jnp.where(ref.closer[:, None, None, None], ref.trajectories, sim)
    return Decomposition(prims, logits, score, sel.scores, sim, sel.slots, distinct, post)

  def decompose(observation: dict, key: jax.Array) -> Decomposition:
    batched = check_observation(observation, run_config)
    lead = np.shape(observation["voxels"])[:1] if batched else ()
    if fit.depth:
      if "depth" not in observation:
        raise ValueError("observation lacks 'depth', which this config's fit reads "
                         "(fit.depth)")
      check_depth(observation["depth"], camera, lead)  # shape, finite, > 0
    if fit.image:
      check_image(observation["image"], camera, lead)  # shape and the camera's size
    given = (PUSH_MAGNITUDES,) if PUSH_MAGNITUDES in observation else ()
    if given:
      check_magnitudes(observation[PUSH_MAGNITUDES], pushes, lead)
    obs = {k: jnp.asarray(observation[k]) for k in keys + given}
    if not batched:
      obs = jax.tree.map(lambda x: x[None], obs)
    out = run(state, est_state, obs, key)
    return out if batched else jax.tree.map(lambda x: x[0], out)

  decompose.config = config  # what it runs, for reports and the evaluation
  decompose.settings = settings  # the engine that simulates the candidates
  return decompose


def object_keys(key: jax.Array, count: int) -> jax.Array:
  """(count,) the key each object of a batch samples with; the evaluation's rows of the
  same settings draw the same candidates from them."""
  return jax.random.split(key, count)
