"""`DecomposeConfig`: every setting of `decompose`, typed, checked in one place.

A model carries its own: `DecomposeConfig.from_eval(config.eval)` reads the preset's `eval`
section saved with every trained and exported model, so that `make_decompose_fn(model)`
and `python -m ppdjax.evaluate` run the settings the model's tables report. Presets:
`paper()` (the paper's inputs: voxels and image) and `best()` (observations with a depth
image: the depth fit and refinement). The choices behind each value: docs/inference.md.
"""

from __future__ import annotations

import dataclasses
import math

from ppdjax.configs import schema
from ppdjax.configs.schema import ConfigError
from ppdjax.infer import faces
from ppdjax.infer.refine import check_jacobian
from ppdjax.infer.sampling import check_screen, check_selection_horizon
from ppdjax.infer.search import check_continuation, check_rounds
from ppdjax.sim.rollout_mjx import check_simulator


def _finite_at_least_zero(x) -> bool:
  """A number (not a bool) that is finite and >= 0: NaN fails every comparison, so `x < 0`
  alone would let it through."""
  return (isinstance(x, (int, float)) and not isinstance(x, bool)
          and math.isfinite(x) and x >= 0)


@dataclasses.dataclass(frozen=True)
class FitConfig:
  """Which boxes the densities go on.

  Attributes:
    enabled: boxes fitted to the voxels (`ppdjax.fit_boxes`, from the network's); False:
      the network's own boxes, as the paper's PPD rows.
    image: then each face moved within half a voxel onto the image's edges (the paper's
      inputs: voxels and image; needs the camera).
    depth: then the faces the camera sees refined against the depth image (needs the
      camera and observation["depth"]).
    face_spread: > 0 (voxels) draws each candidate's faces too, within this of the fitted
      ones (`faces.spread_faces`).
  """
  enabled: bool = True
  image: bool = False
  depth: bool = False
  face_spread: float = 0.0

  @property
  def with_(self) -> tuple[str, ...]:
    """The observations the fit reads beside the voxels."""
    return (("image",) if self.image else ()) + (("depth",) if self.depth else ())


@dataclasses.dataclass(frozen=True)
class SelectConfig:
  """+Sample (paper Sec. 4.3): candidates drawn from the density scores, the closest kept.

  Attributes:
    samples: candidates per object (candidate 0: the scores' arg-max; 1: the arg-max only).
    prior_weight: τ (m per nat): the winner minimises distance − τ · log prior (0: the
      paper's closest trajectory).
    network_prior_weight: τ where the boxes are the network's own (no fit; and the
      evaluation's PPD+Sample row beside a fitted headline); None: prior_weight. A voxel
      off, the network's boxes need densities pulled toward its scores: the closest
      trajectory alone picks densities that make up for the geometry (`tau`).
    horizon: > 0 compares trajectories over their first this many steps (0: all).
    mass_match: a second pass with every candidate scaled to the closest's total mass.
    screen_steps: > 0 simulates every candidate over this many steps and only the
      `screen_keep` closest over the whole trajectory (0: every candidate whole).
    screen_keep: survivors of the screen.
    rounds: > 1 iterates the draw (+Search, `infer.search`): each later round draws
      `samples` more near the closest candidates so far (without mass_match, a screen or
      fit.face_spread).
    inertia: the candidates' boxes also carry inertia scales, searched beside the
      densities (`search.INERTIA_LEVELS`: hollow or filled blocks; +Search).
    continuation: > 0 (with rounds > 1): round r's elite is chosen over the first
      continuation × 2^r steps, then over the horizon (`search.continuation_horizons`).
  """
  samples: int = 512
  prior_weight: float = 0.0
  horizon: int = 0
  mass_match: bool = False
  screen_steps: int = 0
  screen_keep: int = 64
  network_prior_weight: float | None = None
  rounds: int = 1
  inertia: bool = False
  continuation: int = 0

  @property
  def searches(self) -> bool:
    """Whether `infer.search` draws the candidates (else +Sample's one draw)."""
    return self.rounds > 1 or self.inertia

  def tau(self, fitted: bool) -> float:
    """+Sample's τ on fitted boxes or on the network's own."""
    if fitted or self.network_prior_weight is None:
      return self.prior_weight
    return self.network_prior_weight


@dataclasses.dataclass(frozen=True)
class RefineConfig:
  """Levenberg–Marquardt on the densities through the simulator, from the candidate
  closest over the whole trajectory; kept only where it comes closer.

  Attributes:
    enabled: refine at all.
    steps: LM iterations.
    prior_weight: > 0 makes it a MAP step under the density scores (0: least squares).
    jacobian: "forward" (forward mode), "differences" or "central" (`refine.JACOBIANS`).
    inertia: also fit each box's inertia scale (a hollow or filled block: the mass
      distribution within the box; `refine.INERTIA_SCALE_RANGE`); with `enabled`, the
      answer's boxes then carry `inertia_scale`.
    starts: refine from this many of the closest distinct candidates and keep the closest
      refined (`refine.refine_from_candidates`; least squares only; not in the blocks
      evaluation, whose tables refine one start).
  """
  enabled: bool = False
  steps: int = 12
  prior_weight: float = 0.0
  jacobian: str = "forward"
  inertia: bool = False
  starts: int = 1


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
  """A density estimator that reads the fitted boxes and the motion
  (`python -m ppdjax.train_estimator`): its log-probabilities, times `weight`, join the
  network's scores. `path` "" for none."""
  path: str = ""
  weight: float = 1.0


@dataclasses.dataclass(frozen=True)
class PosteriorConfig:
  """How sure each density is (`infer.posterior`): the candidates' posterior.

  Attributes:
    scale: the likelihood exp(−(d − d_min) / T) has T = scale × the closest candidate's
      distance d_min; one scale per box count (the k-th for k + 1 boxes, the last for
      more), chosen on validation towers for 90 % coverage.
    level: the intervals' probability.
    identified_width: a box is flagged identified when its interval spans at most this
      many slots beyond one (0: a single slot).
    prior_power: the density scores enter the posterior raised to this power (< 1: the
      network's scores trusted less than they say).
  """
  scale: tuple[float, ...] = (1.0,)
  level: float = 0.9
  identified_width: int = 2
  prior_power: float = 1.0

  def __post_init__(self):  # a number, or a list read from JSON, as the tuple it means
    if isinstance(self.scale, (int, float)) and not isinstance(self.scale, bool):
      object.__setattr__(self, "scale", (self.scale,))
    elif isinstance(self.scale, list):
      object.__setattr__(self, "scale", tuple(self.scale))


PARTS = {"fit": FitConfig, "select": SelectConfig, "refine": RefineConfig,
         "estimator": EstimatorConfig, "posterior": PosteriorConfig}


@dataclasses.dataclass(frozen=True)
class DecomposeConfig:
  """Every setting of `decompose`; `validate` names the first bad one (ConfigError).

  Beside the parts, `simulator` picks the engine that simulates the selection's
  candidates: "auto" (MuJoCo's C engine on every core where JAX runs on a CPU, the JAX
  engine of the model's data on an accelerator), "jax" or "mujoco"
  (`rollout_mjx.engine_settings`). C is the reference both JAX engines follow
  (docs/physics.md); refinement always runs the JAX engine of the observations.
  """
  fit: FitConfig = FitConfig()
  select: SelectConfig = SelectConfig()
  refine: RefineConfig = RefineConfig()
  estimator: EstimatorConfig = EstimatorConfig()
  posterior: PosteriorConfig = PosteriorConfig()
  simulator: str = "auto"

  def __post_init__(self):
    self.validate()

  def validate(self) -> None:
    """Raises ConfigError (a ValueError) naming the first setting that cannot run."""
    f, s, r = self.fit, self.select, self.refine
    if isinstance(s.samples, bool) or not isinstance(s.samples, int) or s.samples < 1:
      raise ConfigError(f"select.samples must be a whole number >= 1, got {s.samples!r}")
    if (f.image or f.depth or f.face_spread) and not f.enabled:
      raise ConfigError("fit.image, fit.depth and fit.face_spread refine fitted boxes: they "
                       "need fit.enabled")
    try:  # the stages' own checks, named as settings
      faces.check_spread(f.face_spread, f.enabled)
      check_selection_horizon(s.horizon)
      check_screen(s.screen_steps, s.screen_keep, s.samples, 0)
      check_rounds(s.rounds)
      check_continuation(s.continuation, s.rounds, s.horizon)
      check_jacobian(r.jacobian)
      check_simulator(self.simulator)
    except ValueError as e:
      raise ConfigError(str(e)) from e
    for name in ("prior_weight", "network_prior_weight"):
      value = getattr(s, name)
      if not (name == "network_prior_weight" and value is None or _finite_at_least_zero(value)):
        raise ConfigError(f"select.{name} must be finite and >= 0, got {value!r}")
    if not isinstance(s.inertia, bool):
      raise ConfigError(f"select.inertia must be True or False, got {s.inertia!r}")
    if s.searches and (s.mass_match or s.screen_steps or f.face_spread):
      raise ConfigError("select.rounds > 1 and select.inertia (+Search) draw candidates of "
                        "their own: they run without select.mass_match, select.screen_steps "
                        "and fit.face_spread")
    if isinstance(r.steps, bool) or not isinstance(r.steps, int) or r.steps < 1:
      raise ConfigError(f"refine.steps must be a whole number >= 1, got {r.steps!r}")
    if isinstance(r.starts, bool) or not isinstance(r.starts, int) or r.starts < 1:
      raise ConfigError(f"refine.starts must be a whole number >= 1, got {r.starts!r}")
    if not _finite_at_least_zero(r.prior_weight):
      raise ConfigError(f"refine.prior_weight must be finite and >= 0, got {r.prior_weight!r}")
    if r.enabled and r.starts > 1 and (r.prior_weight or r.starts > s.samples * s.rounds):
      raise ConfigError("refine.starts > 1 refines that many candidates by least squares: "
                        "it needs refine.prior_weight 0 and at most select.samples x "
                        f"select.rounds candidates, got {r.starts}")
    if self.estimator.path and not f.enabled:
      raise ConfigError("the estimator reads fitted boxes: it needs fit.enabled")
    q = self.posterior
    if (not isinstance(q.scale, tuple) or not q.scale
        or not all(_finite_at_least_zero(x) and x > 0 for x in q.scale)):
      raise ConfigError("posterior.scale must be a tuple of finite numbers > 0 (one per box "
                        f"count), got {q.scale!r}")
    if not (_finite_at_least_zero(q.level) and 0 < q.level < 1):
      raise ConfigError(f"posterior.level must lie in (0, 1), got {q.level!r}")
    if (isinstance(q.identified_width, bool) or not isinstance(q.identified_width, int)
        or q.identified_width < 0):
      raise ConfigError("posterior.identified_width must be a whole number of slots >= 0, "
                        f"got {q.identified_width!r}")
    if not (_finite_at_least_zero(q.prior_power) and q.prior_power > 0):
      raise ConfigError(f"posterior.prior_power must be finite and > 0, got {q.prior_power!r}")

  def replace(self, **changes) -> "DecomposeConfig":
    """A copy with dotted changes, e.g. `replace(**{"select.samples": 64})`, whole parts
    (`replace(refine=RefineConfig(enabled=True))`) or the simulator
    (`replace(simulator="jax")`)."""
    parts = {}
    for key, value in changes.items():
      part, _, field = key.partition(".")
      if part == "simulator" and not field:
        parts[part] = value
        continue
      if part not in PARTS:
        raise ValueError(f"DecomposeConfig has no part {part!r} ({', '.join(PARTS)}, or "
                         "simulator)")
      if not field:
        parts[part] = value
        continue
      current = parts.get(part, getattr(self, part))
      if field not in {x.name for x in dataclasses.fields(current)}:
        raise ValueError(f"DecomposeConfig.{part} has no setting {field!r}")
      parts[part] = dataclasses.replace(current, **{field: value})
    return dataclasses.replace(self, **parts)

  def to_dict(self) -> dict:
    """The settings as JSON writes and reads them (the posterior's scales a list)."""
    d = dataclasses.asdict(self)
    d["posterior"]["scale"] = list(d["posterior"]["scale"])
    return d

  @classmethod
  def from_dict(cls, d: dict) -> "DecomposeConfig":
    unknown = set(d) - set(PARTS) - {"simulator"}
    if unknown:
      raise ValueError(f"DecomposeConfig has no part {sorted(unknown)}")
    return cls(**{k: PARTS[k](**v) if k in PARTS else v for k, v in d.items()})

  @classmethod
  def from_eval(cls, eval_section) -> "DecomposeConfig":
    """The decomposition settings of a preset's (or a saved run's) `eval` section
    (`configs.schema.EvalConfig`: the one mapping between the two)."""
    values = (dataclasses.asdict(eval_section) if dataclasses.is_dataclass(eval_section)
              else dict(eval_section))
    e = schema._section("eval", values)  # pylint: disable=protected-access
    # depth implies the voxel fit it refines; image_fit and face_spread without a fit are
    # refused by `validate`, not dropped
    return cls(
        fit=FitConfig(enabled=e.fit or e.depth, image=e.image_fit, depth=e.depth,
                      face_spread=e.face_spread),
        select=SelectConfig(samples=e.samples, prior_weight=e.prior_weight,
                            horizon=e.selection_horizon, mass_match=e.mass_match,
                            screen_steps=e.screen_steps, screen_keep=e.screen_keep,
                            rounds=e.rounds, inertia=e.sample_inertia,
                            continuation=e.search_continuation,
                            network_prior_weight=(None if e.network_prior_weight < 0
                                                  else e.network_prior_weight)),
        refine=RefineConfig(enabled=e.refine, steps=e.refine_steps,
                            prior_weight=e.refine_prior, jacobian=e.refine_jacobian,
                            inertia=e.refine_inertia, starts=e.refine_starts),
        estimator=EstimatorConfig(path=e.estimator, weight=e.estimator_weight),
        posterior=PosteriorConfig(scale=tuple(e.posterior_scale), level=e.posterior_level,
                                  identified_width=e.identified_width,
                                  prior_power=e.posterior_prior_power),
        simulator=e.simulator)

  def to_eval(self) -> dict:
    """The `eval` section's keys for these settings (`from_eval`'s inverse)."""
    f, s, r, e, q = self.fit, self.select, self.refine, self.estimator, self.posterior
    return {"samples": s.samples, "fit": f.enabled, "image_fit": f.image, "depth": f.depth,
            "face_spread": f.face_spread, "prior_weight": s.prior_weight,
            "network_prior_weight": (-1.0 if s.network_prior_weight is None
                                     else s.network_prior_weight),
            "selection_horizon": s.horizon, "mass_match": s.mass_match,
            "screen_steps": s.screen_steps, "screen_keep": s.screen_keep,
            "rounds": s.rounds, "sample_inertia": s.inertia,
            "search_continuation": s.continuation,
            "refine": r.enabled, "refine_steps": r.steps, "refine_prior": r.prior_weight,
            "refine_jacobian": r.jacobian, "refine_inertia": r.inertia,
            "refine_starts": r.starts, "estimator": e.path,
            "estimator_weight": e.weight, "posterior_scale": q.scale,
            "posterior_level": q.level, "identified_width": q.identified_width,
            "posterior_prior_power": q.prior_power,
            "simulator": self.simulator}

  @classmethod
  def paper(cls) -> "DecomposeConfig":
    """The paper's inputs (voxels, image, trajectories): boxes fitted to the voxels and the
    image's edges, 512 candidates compared over their first 32 steps (chosen on the
    validation split), no refinement: the blocks' headline +Fit+Sample row (and τ = 0.005
    on the network's own boxes, should the fit be turned off; the `paper` preset's); the
    posterior calibrated on validation towers (experiments/posterior)."""
    return cls(fit=FitConfig(image=True),
               select=SelectConfig(horizon=32, network_prior_weight=0.005),
               posterior=PosteriorConfig(scale=(0.02, 0.02, 0.5, 2.8, 4.0), prior_power=0.7,
                                         identified_width=5))

  @classmethod
  def best(cls) -> "DecomposeConfig":
    """Observations with a depth image: boxes fitted to the voxels and the depth, 512
    candidates screened over 32 steps (the 64 closest simulated whole), then refinement
    by forward differences: the blocks' best row; the posterior calibrated on validation
    towers for these settings (experiments/posterior)."""
    return cls(fit=FitConfig(depth=True),
               select=SelectConfig(screen_steps=32, screen_keep=64),
               refine=RefineConfig(enabled=True, jacobian="differences"),
               posterior=PosteriorConfig(scale=(0.01, 0.01, 1.0, 1.4, 2.8), prior_power=0.5,
                                         identified_width=5))
