"""The one config schema: a frozen dataclass per section, defaults in one place.

Presets (`tiny`, `paper`, `tools`, `video`) are `get_config()` ConfigDicts for the command
lines' `--config.<section>.<key>=<value>` overrides; `read(config)` types one (`RunConfig`),
naming a bad key; `complete(config)` fills the keys a saved run predates with these defaults.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import ml_collections


@dataclasses.dataclass(frozen=True)
class DemoConfig:
  """`make demo`: one random tower under the paper's four pushes, the shipped example."""
  num_blocks: int = 4  # 2..5
  steps: int = 256
  backend: str = "mjx"  # the engine whose trajectories are shown
  reference_backend: str = "mujoco"  # compared against; "" to skip
  example_samples: int = 512  # density samples for the shipped example (the model's)
  example_image_fit: bool = False  # the image fit (2 cores: ~12 s to compile, 1.3 s to run)


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """The dataset (`python -m ppdjax.generate`)."""
  kind: str = "towers"  # "towers", "tools" (configs/tools.py) or "pendulum" (video)
  num_towers: int = 16
  towers_per_shard: int = 4
  configs_per_tower: int = 8
  image_size: int = 64
  steps: int = 256
  num_blocks: int = 0  # blocks per tower: 0 draws 2..5; 2 for the tools' pretraining
  rotate: float = 0.0  # radians; > 0 adds the paper's rotation noise (tools pretraining)
  size_noise: float = 0.0
  backend: str = "mjx"  # the data's and decompose's engine: "mjx", "box_plane" or "mujoco"
  split_fractions: tuple = (0.8, 0.1, 0.1)
  render_workers: int = 0  # processes rendering in parallel (0: this process)
  num_tools: int = 0  # tools (configs/tools.py)
  tools_per_shard: int = 0
  configs_per_tool: int = 1
  tool_push_force: float = 1e3
  tool_protocol: str = "realistic"  # or "paper": the tool's boxes are its body (tools_paper.py)
  tool_materials: str = "category"  # or "plausible" (tools.PLAUSIBLE_MATERIALS, per piece)
  tool_push: str = "fixed"  # or "by_volume": x volume / tool_scene.REFERENCE_VOLUME
  block_counts: tuple = ()  # video towers: block counts drawn uniformly (configs/video.py)
  look: str = "material"  # what each block shows (materials.LOOKS): look-alike towers
  hollow: float = 0.0  # the chance that a block is a shell around a core (dataset.hollow)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """The PPD network (paper appendix; ppdjax.nn.model)."""
  feature: int = 64  # f_V, f_I, f_T and f
  hidden: int = 64  # LSTM hidden size (trajectory encoder and generator)
  generator_layers: int = 3
  dropout: float = 0.5
  voxel_width: int = 1  # channel multiplier of the voxel encoder (1: the paper's)
  voxel_coords: bool = False  # voxel centres as 3 extra input channels (CoordConv)
  voxel_keep: int = 1  # pool the voxels down to keep^3 (1: the paper's; 4 keeps position)
  resnet_width: int = 16  # 64 is ResNet-18 proper (paper preset); 16 for CPUs
  image_dtype: str = "float32"  # the ResNet's compute type ("bfloat16": convolutions)
  image_weights: str = ""  # optional .npz of converted torchvision ResNet-18 weights
  num_pushes: int = 4
  trajectory_unroll: int = 1  # time steps per scan iteration of the trajectory LSTMs
  max_primitives: int = 5
  # the physics encoder's input: "trajectory" (the paper's) or "depth_video" (its RGB-D
  # row: video_frames per push at video_size^2 pixels, made on the device; nn.depth_video)
  physics_input: str = "trajectory"
  video_frames: int = 16
  video_size: int = 64
  use_voxels: bool = True  # ablation switches: a disabled encoder's feature is 0
  use_image: bool = True
  use_trajectory: bool = True
  # True: the density head reads an LSTM stack of its own, so the density loss does not move
  # the geometry's LSTMs or the voxel encoder (tools); False: the paper's one generator
  density_branch: bool = False
  # > 0: the density branch also reads the velocities over the first this many recorded
  # steps after each push (ppdjax.nn.motion.early_motion; needs density_branch)
  early_motion_steps: int = 0


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Training (`python -m ppdjax.train`)."""
  seed: int = 0
  batch_size: int = 16  # global, split over all devices
  # BatchNorm's statistics on several devices: "global" (all-reduced) or "per_device"
  batch_norm: str = "global"
  learning_rate: float = 1e-3  # Adam, beta = (0.9, 0.999), as in the appendix
  schedule: str = "constant"  # or "cosine": decay to 0 over all steps
  warmup_steps: int = 0  # > 0: the rate rises linearly from 0 over these steps
  clip_norm: float = 0.0  # > 0: gradients clipped to this global norm before Adam
  stream_steps: int = 0  # phase 0: voxels of fresh towers only (dataset.stream)
  geometry_steps: int = 20  # phase 1: geometry only (w = 0)
  joint_steps: int = 40  # phase 2: geometry + w x density
  density_weight: float = 0.5  # w of Eq. 4-5 (docs/training.md says why 0.5)
  density_ramp_steps: int = 0  # > 0: w rises linearly over the joint phase's first steps
  end_weight: typing.Optional[float] = 1.0  # in every phase; None (older runs): w
  geometry_weight: float = 1.0  # the dataset's geometry loss
  stream_weight: float = 0.0  # > 0: phases 1-2 add a stream batch's geometry loss
  augment: bool = True  # stream batches under random symmetries of the square about z
  physics_stream_weight: float = 0.0  # > 0: simulated fresh towers' loss (training.streams)
  init_from: str = ""  # a workdir whose matching parameters start this run
  log_every: int = 10
  eval_every: int = 30  # validation and checkpoint
  eval_batches: int = 4  # validation batches per evaluation (0: the whole split)
  keep_checkpoints: int = 3
  prefetch: int = 2  # batches read ahead in a background thread


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
  """The density estimator (ppdjax.nn.estimator; `python -m ppdjax.train_estimator`)."""
  seed: int = 0
  pool_size: int = 512  # simulated training towers (fresh geometry each)
  val_size: int = 128
  steps: int = 100
  batch_size: int = 32
  learning_rate: float = 1e-3  # AdamW, warm-up then cosine decay
  warmup_steps: int = 10
  weight_decay: float = 1e-4
  clip_norm: float = 1.0
  label_sigma: float = 1.0  # slots: Gaussian targets about the true slot
  box_noise: float = 0.002  # m: face jitter of the boxes it reads (fitted boxes' error)
  channels: tuple = (16, 16, 32, 32)  # 1-D convolutions over time, stride 2 each
  hidden: int = 64
  layers: int = 2
  steps_in: int = 256  # = data.steps
  num_pushes: int = 4  # = model.num_pushes
  max_primitives: int = 5  # = model.max_primitives
  eval_every: int = 50


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """Decomposition settings (the model's saved `DecomposeConfig`, `infer.config`) and what
  the evaluation adds for its tables (`python -m ppdjax.evaluate`)."""
  # --- decomposition: `DecomposeConfig.from_eval` reads these -------------------------
  samples: int = 8  # density candidates per object (the paper: 512)
  fit: bool = False  # boxes fitted to the voxels, not the network's (infer.fit)
  image_fit: bool = False  # ... then their faces moved onto the image's edges (image_fit)
  depth: bool = False  # ... then refined against the depth image (depth_fit; implies fit)
  face_spread: float = 0.0  # > 0 voxels: candidates' faces drawn too (infer.faces)
  prior_weight: float = 0.0  # +Sample: distance - tau log prior (m per nat; 0: the paper's)
  network_prior_weight: float = -1.0  # tau on the network's boxes (< 0: prior_weight's)
  selection_horizon: int = 0  # +Sample's distance over the first N steps (0: all, the paper's)
  mass_match: bool = False  # candidates scaled to the closest's total mass, simulated again
  screen_steps: int = 0  # > 0: every candidate over N steps, the screen_keep closest whole
  screen_keep: int = 64
  rounds: int = 1  # > 1: +Search, the draw iterated near the closest (infer.search)
  sample_inertia: bool = False  # +Search: candidates carry inertia scales (hollow blocks)
  search_continuation: int = 0  # +Search: round r's elite over 2^r x this many steps
  refine: bool = False  # LM refinement of the densities through the simulator
  refine_steps: int = 12
  refine_prior: float = 0.0  # > 0: refinement is a MAP step under the density scores
  refine_jacobian: str = "forward"  # forward | differences | central (infer.refine)
  refine_inertia: bool = False  # ... also each box's inertia scale (hollow blocks)
  refine_starts: int = 1  # ... from this many closest candidates, the closest refined kept
  estimator: str = ""  # a trained density estimator's folder: its scores join the network's
  estimator_weight: float = 1.0  # its log-probabilities' weight beside the network's
  simulator: str = "auto"  # the candidates' engine: auto (C on a CPU) | jax | mujoco
  posterior_scale: tuple = (1.0,)  # each density's posterior: T = scale x least distance, by K
  posterior_level: float = 0.9  # ... its intervals' probability
  posterior_prior_power: float = 1.0  # ... the density scores raised to this power
  identified_width: int = 2  # ... identified: the interval this many slots beyond one at most
  # --- evaluation only ------------------------------------------------------------------
  seed: int = 0  # the candidates' draws (object i of batch b: `decompose`'s key for it)
  batch_size: int = 8
  baselines: bool = True  # Frequent, Nearest, Oracle and Table 4's sampling baselines
  joint: bool = False  # also +Joint: faces and densities fitted together (infer.joint)
  true_shapes: bool = False  # also the oracle rows on the true boxes
  table4_objects: int = 0  # Table 4's sampling baselines on about N objects (0: every one)
  studies: bool = False  # sweeps over the candidates (τ, temperatures, screens, oracle picks)
  horizon_sweep: bool = False  # ... and every horizon: free in rollouts, not in host time
  refine_horizon: int = 0  # runs saved before 2026-11-28 (+Refine's start; only 0 accepted)


@dataclasses.dataclass(frozen=True)
class PretrainConfig:
  """The tools' pretraining towers (configs/tools.py)."""
  num_towers: int = 16
  num_blocks: int = 2
  rotate: float = 0.2
  size_noise: float = 0.1


@dataclasses.dataclass(frozen=True)
class FinetuneConfig:
  """The tools' fine-tuning stage (configs/tools.py)."""
  geometry_steps: int = 20
  geometry_weight: float = 1.0
  joint_steps: int = 40
  learning_rate: float = 1e-3
  eval_every: int = 30


@dataclasses.dataclass(frozen=True)
class FloorConfig:
  """The realistic tools benchmark's floor (`ppdjax.eval.tool_floor`)."""
  tools: int = 2  # test tools read (the first of the test split)
  configs: int = 1  # density configurations of each (data.configs_per_tool at most)
  geometries: int = 4  # geometry samples each tool's densities are read on
  seed: int = 0  # the chain's and the tracking noise's draws


@dataclasses.dataclass(frozen=True)
class VideoTestConfig:
  """The video towers' test clips (configs/video.py)."""
  seed: int = 1_000_019
  counts: tuple = (4, 2, 2)  # towers of 2, 3, 4 blocks
  fps: float = 60.0
  frame: tuple = (240, 320)
  noise: float = 3.0  # grey levels
  lighting: float = 0.1  # brightness drift, a fraction
  stickers: str = "sides"  # video.synthetic.STICKER_LAYOUTS: "sides", "sides_top", "all"
  fovy: float = 30.0  # degrees: the video camera's vertical field of view (synthetic.FOVY)
  appearance: bool = False  # also a model that reads no trajectory, reported beside


@dataclasses.dataclass(frozen=True)
class RunConfig:
  """A whole preset, typed. `pretrain`, `finetune`, `floor` and `test` belong to the tools
  and video pipelines: None where a preset has no such section."""
  name: str = "tiny"
  seed: int = 0
  demo: DemoConfig = DemoConfig()
  data: DataConfig = DataConfig()
  model: ModelConfig = ModelConfig()
  train: TrainConfig = TrainConfig()
  estimator: EstimatorConfig = EstimatorConfig()
  eval: EvalConfig = EvalConfig()
  pretrain: typing.Optional[PretrainConfig] = None
  finetune: typing.Optional[FinetuneConfig] = None
  floor: typing.Optional[FloorConfig] = None
  test: typing.Optional[VideoTestConfig] = None


SECTIONS = {f.name: f.type for f in dataclasses.fields(RunConfig)}
_SECTION_TYPES = {"demo": DemoConfig, "data": DataConfig, "model": ModelConfig,
                  "train": TrainConfig, "estimator": EstimatorConfig, "eval": EvalConfig,
                  "pretrain": PretrainConfig, "finetune": FinetuneConfig,
                  "floor": FloorConfig, "test": VideoTestConfig}
OPTIONAL_SECTIONS = ("pretrain", "finetune", "floor", "test")


class ConfigError(ValueError):
  """A config key that the schema does not know, or a value of the wrong type."""


def _check_value(where: str, value, default, annotation):
  """`value` converted to the field's type, or ConfigError naming `where`."""
  optional = "Optional" in str(annotation)
  if value is None:
    if optional:
      return None
    raise ConfigError(f"config.{where} must not be None")
  kind = type(default) if default is not None else float
  if kind is bool:
    if not isinstance(value, bool):
      raise ConfigError(f"config.{where} must be True or False, got {value!r}")
    return value
  if kind is int:
    if isinstance(value, bool) or not isinstance(value, int):
      if isinstance(value, float) and value.is_integer():
        return int(value)
      raise ConfigError(f"config.{where} must be a whole number, got {value!r}")
    return value
  if kind is float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
      raise ConfigError(f"config.{where} must be a number, got {value!r}")
    if not math.isfinite(value):  # NaN passes every range check that compares
      raise ConfigError(f"config.{where} must be finite, got {value!r}")
    return float(value)
  if kind is str:
    if not isinstance(value, str):
      raise ConfigError(f"config.{where} must be a string, got {value!r}")
    return value
  if kind is tuple:
    if not isinstance(value, (tuple, list)):
      raise ConfigError(f"config.{where} must be a sequence, got {value!r}")
    return tuple(value)
  return value


def _section(name: str, values: dict):
  cls = _SECTION_TYPES[name]
  fields = {f.name: f for f in dataclasses.fields(cls)}
  unknown = sorted(set(values) - set(fields))
  if unknown:
    raise ConfigError(f"config.{name} has no key {', '.join(unknown)} (known: "
                      f"{', '.join(sorted(fields))})")
  section = cls(**{k: _check_value(f"{name}.{k}", v, fields[k].default, fields[k].type)
                   for k, v in values.items()})
  if name == "eval" and section.refine_horizon != 0:
    raise ConfigError("config.eval.refine_horizon: refinement starts from the candidate "
                      f"closest over all steps (0); got {section.refine_horizon}")
  return section


def read(config) -> RunConfig:
  """A preset or a saved run's config (ConfigDict or dict) as typed sections; keys it
  lacks take the schema's defaults. Raises ConfigError naming an unknown or ill-typed key."""
  d = config.to_dict() if hasattr(config, "to_dict") else dict(config)
  unknown = sorted(set(d) - set(SECTIONS))
  if unknown:
    raise ConfigError(f"config has no section {', '.join(unknown)} (known: "
                      f"{', '.join(SECTIONS)})")
  out = {}
  for name, value in d.items():
    if name in _SECTION_TYPES:
      if not isinstance(value, dict):
        raise ConfigError(f"config.{name} must be a section, got {value!r}")
      out[name] = _section(name, value)
    else:
      out[name] = _check_value(name, value, getattr(RunConfig(), name), SECTIONS[name])
  return RunConfig(**out)


def to_config_dict(run: RunConfig) -> ml_collections.ConfigDict:
  """`run` as the ConfigDict the command lines override (optional sections only where set)."""
  d = dataclasses.asdict(run)
  return ml_collections.ConfigDict({k: v for k, v in d.items() if v is not None})


def complete(config) -> ml_collections.ConfigDict:
  """`config` (a preset or a saved run's) checked against the schema, with every key it
  lacks filled in from the defaults; sections it lacks stay absent only if optional."""
  return to_config_dict(read(config))


def default_config() -> ml_collections.ConfigDict:
  """The schema's defaults (the `tiny` preset) as a ConfigDict."""
  return to_config_dict(RunConfig())


SAVED_BEFORE = {("train", "end_weight"): None}  # earlier defaults, kept by runs saved without


def complete_saved(saved: dict) -> ml_collections.ConfigDict:
  """`complete` for a run's saved config.json (a dict), keys it predates as SAVED_BEFORE."""
  d = {k: dict(v) if isinstance(v, dict) else v for k, v in saved.items()}
  for (section, key), value in SAVED_BEFORE.items():
    if isinstance(d.get(section), dict):
      d[section].setdefault(key, value)
  return complete(d)
