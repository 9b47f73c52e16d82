"""The PPD network (paper Sec. 4 and appendix) in Flax NNX: three encoders, a recurrent generator.

Observations are dicts of batched arrays: "voxels" (B, 32, 32, 32) uint8, "image"
(B, H, W, 3) uint8, "trajectories" (B, P, T, 7) float32 (world poses after each step).
The generator emits S = max_primitives + 1 steps; each step is a primitive or the end token.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx, struct

from ppdjax.conventions import DEPTH_VIDEO, NUM_DENSITY_SLOTS, OBS_KEYS, slot_to_density_jax
from ppdjax.nn.depth_video import DepthVideoEncoder
from ppdjax.nn.motion import TRAJ_FEATURES, early_motion, trajectory_features
from ppdjax.nn.recurrent import GroupedLSTM, LSTMCell, per_push_bidirectional
from ppdjax.nn.resnet import ResNet18
from ppdjax.primitives import Primitives

START, END = NUM_DENSITY_SLOTS, NUM_DENSITY_SLOTS + 1  # the density head's two tokens
NUM_CLASSES = NUM_DENSITY_SLOTS + 2
PRIM_DIM = NUM_CLASSES + 3 + 3 + 4  # a primitive fed back to the generator
SIZE_SCALE = TRANS_SCALE = 0.5  # C_S and C_T of Eq. 3
# model.physics_input -> the observation the physics encoder reads
PHYSICS_INPUTS = {"trajectory": "trajectories", "depth_video": DEPTH_VIDEO}
REDUCED = 16  # channels per cell of a position-keeping voxel encoder before flattening


@struct.dataclass
class Prediction:
  """The generator's output per step: (B, S, ...)."""
  density_logits: jax.Array  # (B, S, 102): 100 slots, start, end
  half_size: jax.Array  # (B, S, 3) in [0, C_S]
  pos: jax.Array  # (B, S, 3) in [-C_T, C_T]
  quat: jax.Array  # (B, S, 4) unit


def _max_pool_2x(x: jax.Array) -> jax.Array:
  """2×2×2 max-pooling, stride 2, of (B, D, H, W, C) (a reshape: far faster than
  reduce_window on CPUs)."""
  b, d, h, w, c = x.shape
  return x.reshape(b, d // 2, 2, h // 2, 2, w // 2, 2, c).max(axis=(2, 4, 6))


class Conv3x3x3(nnx.Module):
  """A 3×3×3 convolution, padding 1. On CPUs it runs as patches × kernel (4× faster than
  XLA's CPU convolution for these few channels); elsewhere as a native convolution."""

  def __init__(self, cin: int, cout: int, *, rngs: nnx.Rngs):
    self.kernel = nnx.Param(nnx.initializers.lecun_normal()(rngs.params(), (3, 3, 3, cin, cout)))
    self.bias = nnx.Param(jnp.zeros((cout,)))

  def __call__(self, x_BDHWC: jax.Array) -> jax.Array:
    k = self.kernel.value
    if jax.default_backend() != "cpu":
      y = jax.lax.conv_general_dilated(x_BDHWC, k, (1, 1, 1), "SAME",
                                       dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
    else:
      b, d, h, w, c = x_BDHWC.shape
      xp = jnp.pad(x_BDHWC, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)))
      cols = jnp.concatenate([xp[:, i:i + d, j:j + h, l:l + w]
                              for i in range(3) for j in range(3) for l in range(3)], -1)
      y = cols @ k.reshape(27 * c, -1)
    return y + self.bias.value


class VoxelEncoder(nnx.Module):
  """Five 3×3×3 convolutions (channels 1→2→4→8→16→32, times `width`), each with BatchNorm and
  LeakyReLU(0.2), then → f_V.

  `keep` = 1 is the appendix's encoder: 2×2×2 max-pooling after every convolution
  (32³ → 1³), then two 1×1×1 convolutions. Pooled to 1³, a feature says what it saw but
  hardly where, and where the boxes sit is what the generator must regress to a fraction
  of a voxel. `keep` = 4 stops pooling at 4³ (the last two convolutions run there) and
  flattens the 4³ grid of features into two fully connected layers, so position
  survives (experiments/results/shape_study.md measures the choice). A 1×1×1 convolution
  first brings the channels down to REDUCED: flattening 4³ × 256 channels (width 8) into
  one layer gave a fan-in of 16,384 that Adam at 4e-3 saturated within the first steps
  (the encoder then told towers apart no better than chance).

  With `coords`, the occupancy is joined by three channels holding each voxel's centre in
  [−0.5, 0.5] (CoordConv).
  """

  def __init__(self, out_features: int, width: int = 1, coords: bool = False, keep: int = 1,
               *, rngs: nnx.Rngs):
    if keep not in (1, 2, 4, 8):
      raise ValueError(f"config.model.voxel_keep must be 1, 2, 4 or 8, got {keep}")
    self.coords, self.pools = coords, 5 - int(keep).bit_length() + 1
    chans = [4 if coords else 1] + [c * width for c in (2, 4, 8, 16, 32)]
    self.convs = nnx.List([Conv3x3x3(a, b, rngs=rngs)
                           for a, b in zip(chans[:-1], chans[1:])])
    self.norms = nnx.List([nnx.BatchNorm(b, momentum=0.9, rngs=rngs) for b in chans[1:]])
    if keep == 1:  # the appendix's 1×1×1 convolutions (the parameters older runs saved)
      self.head1 = nnx.Conv(chans[-1], out_features, (1, 1, 1), rngs=rngs)
      self.head2 = nnx.Conv(out_features, out_features, (1, 1, 1), rngs=rngs)
    else:  # 1×1×1 down to REDUCED channels, then the keep³ grid flattened
      self.reduce = nnx.Conv(chans[-1], REDUCED, (1, 1, 1), rngs=rngs)
      self.head1 = nnx.Linear(REDUCED * keep ** 3, out_features, rngs=rngs)
      self.head2 = nnx.Linear(out_features, out_features, rngs=rngs)

  def __call__(self, voxels_BxDxDxD: jax.Array, train: bool) -> jax.Array:
    x = voxels_BxDxDxD.astype(jnp.float32)[..., None]
    if self.coords:
      d = x.shape[1]
      axis = (jnp.arange(d, dtype=jnp.float32) + 0.5) / d - 0.5
      grid = jnp.stack(jnp.meshgrid(axis, axis, axis, indexing="ij"), -1)
      x = jnp.concatenate([x, jnp.broadcast_to(grid, x.shape[:4] + (3,))], -1)
    for i, (conv, norm) in enumerate(zip(self.convs, self.norms)):
      x = nnx.leaky_relu(norm(conv(x), use_running_average=not train), 0.2)
      if i < self.pools:
        x = _max_pool_2x(x)
    if self.pools < 5:
      x = nnx.leaky_relu(self.reduce(x), 0.2).reshape(x.shape[0], -1)
    x = self.head2(nnx.leaky_relu(self.head1(x), 0.2))
    return x.reshape(x.shape[0], -1)


class TrajectoryEncoder(nnx.Module):
  """A bidirectional LSTM per push; [h→; h←] per push, concatenated, projected → f_T."""

  def __init__(self, num_pushes: int, hidden: int, out_features: int, dropout: float, *,
               rngs: nnx.Rngs, unroll: int = 1):
    self.lstm = GroupedLSTM(2 * num_pushes, TRAJ_FEATURES, hidden, rngs=rngs, unroll=unroll)
    self.dropout = nnx.Dropout(dropout)
    self.proj = nnx.Linear(2 * num_pushes * hidden, out_features, rngs=rngs)

  def __call__(self, traj_BPTx7: jax.Array, train: bool, rngs) -> jax.Array:
    h = per_push_bidirectional(self.lstm, trajectory_features(traj_BPTx7))
    return self.proj(self.dropout(h, deterministic=not train, rngs=rngs))


def primitive_vector(token: jax.Array, half_size, pos, quat) -> jax.Array:
  """(..., 112) what the generator is fed back: [one-hot density token; size; pos; quat]."""
  return jnp.concatenate([jax.nn.one_hot(token, NUM_CLASSES), half_size, pos, quat], -1)


def physics_key(model_config) -> str:
  """The observation a model's physics encoder reads: "trajectories" or DEPTH_VIDEO."""
  kind = model_config.get("physics_input", "trajectory")
  if kind not in PHYSICS_INPUTS:
    raise ValueError(f"config.model.physics_input must be one of {tuple(PHYSICS_INPUTS)}, "
                     f"got {kind!r}")
  return PHYSICS_INPUTS[kind]


class PPD(nnx.Module):
  """Encoders + recurrent primitive generator. `config` is the preset's `model` section."""

  def __init__(self, config: ml_collections.ConfigDict, *, rngs: nnx.Rngs):
    c = config
    self.early_steps = c.get("early_motion_steps", 0) if c.use_trajectory else 0
    if self.early_steps and not c.get("density_branch", False):
      raise ValueError("config.model.early_motion_steps feeds the density branch: set "
                       "config.model.density_branch = True too")
    self.feature, self.hidden, self.max_primitives = c.feature, c.hidden, c.max_primitives
    self.early_size = c.num_pushes * self.early_steps * 6  # early_motion's features
    f = c.feature
    self.voxel_encoder = (VoxelEncoder(f, c.get("voxel_width", 1), c.get("voxel_coords", False),
                                       c.get("voxel_keep", 1), rngs=rngs)
                          if c.use_voxels else None)
    image_dtype = c.get("image_dtype", "float32")
    if image_dtype not in ("float32", "bfloat16"):
      raise ValueError(f"config.model.image_dtype must be 'float32' or 'bfloat16', "
                       f"got {image_dtype!r}")
    self.image_encoder = (ResNet18(f, c.resnet_width, rngs=rngs,
                                   dtype=None if image_dtype == "float32" else jnp.bfloat16)
                          if c.use_image else None)
    # The physics observation: the trajectories, or (the RGB-D row) a depth video per push
    self.physics_key = physics_key(c)
    self.video = None  # (frames, size) of the depth video it reads (`dataset.depth_video`)
    unroll = c.get("trajectory_unroll", 1)
    if not c.use_trajectory:
      self.trajectory_encoder = None
    elif self.physics_key == DEPTH_VIDEO:
      if self.early_steps:
        raise ValueError("config.model.early_motion_steps reads the trajectories; a model "
                         "of physics_input='depth_video' has none")
      self.video = (c.video_frames, c.video_size)
      self.trajectory_encoder = DepthVideoEncoder(c.num_pushes, c.video_size, c.hidden, f,
                                                  c.dropout, rngs=rngs, unroll=unroll)
    else:
      self.trajectory_encoder = TrajectoryEncoder(c.num_pushes, c.hidden, f, c.dropout,
                                                  rngs=rngs, unroll=unroll)
    self.fuse = nnx.Linear(3 * f, f, rngs=rngs)
    self.cells = nnx.List([LSTMCell((PRIM_DIM + f) if i == 0 else c.hidden, c.hidden,
                                    rngs=rngs) for i in range(c.generator_layers)])
    # The density branch (model.density_branch; see `_step`): its own fusion and LSTMs,
    # and, with model.early_motion_steps, the velocities just after each push (`_fused`).
    if c.get("density_branch", False):
      self.density_fuse = nnx.Linear(3 * f + self.early_size, f, rngs=rngs)
      self.density_cells = nnx.List([
          LSTMCell((PRIM_DIM + f + c.hidden) if i == 0 else c.hidden, c.hidden, rngs=rngs)
          for i in range(c.generator_layers)])
    else:
      self.density_fuse = self.density_cells = None
    self.dropout = nnx.Dropout(c.dropout)
    self.density_head = nnx.Linear(c.hidden, NUM_CLASSES, rngs=rngs)
    self.size_head = nnx.Linear(c.hidden, 3, rngs=rngs)
    self.trans_head = nnx.Linear(c.hidden, 3, rngs=rngs)
    self.rot_head = nnx.Linear(c.hidden, 4, rngs=rngs,
                               bias_init=lambda k, s, d=jnp.float32: jnp.array([1., 0, 0, 0], d))

  def _encoder_features(self, obs: dict, train: bool, rngs) -> list[jax.Array]:
    """[f_V, f_I, f_T], each (B, feature), then with model.early_motion_steps the
    `early_motion` features. An ablated encoder's part is 0, and so is the part of an
    observation `obs` lacks (the geometry stream has voxels only)."""
    b = next(obs[k].shape[0] for k in OBS_KEYS + (DEPTH_VIDEO,) if k in obs)
    if self.video is not None and "trajectories" in obs and DEPTH_VIDEO not in obs:
      raise ValueError(f"this model reads a depth video of each push: the observations need "
                       f"{DEPTH_VIDEO!r} (dataset.depth_video.with_depth_video renders it)")
    zero = jnp.zeros((b, self.feature))
    use = lambda enc, key: enc is not None and key in obs
    parts = [
        self.voxel_encoder(obs["voxels"], train) if use(self.voxel_encoder, "voxels") else zero,
        self.image_encoder(obs["image"], train) if use(self.image_encoder, "image") else zero,
        (self.trajectory_encoder(obs[self.physics_key], train, rngs)
         if use(self.trajectory_encoder, self.physics_key) else zero),
    ]
    if self.early_steps:
      parts.append(early_motion(obs["trajectories"], self.early_steps)
                   if "trajectories" in obs else jnp.zeros((b, self.early_size)))
    return parts

  def encode(self, obs: dict, train: bool = False, rngs=None) -> jax.Array:
    """f (B, feature): [f_V; f_I; f_T] through a fully connected layer (see
    `_encoder_features` for ablated or missing inputs)."""
    return self._fused(self._encoder_features(obs, train, rngs))[0]

  def _fused(self, parts: list[jax.Array]) -> tuple[jax.Array, jax.Array | None]:
    """(f, f_D): the generator's features and, with a density branch, the branch's own,
    fused from the voxel feature with its gradient stopped (the density loss does not
    move the voxel encoder, which geometry relies on) and the early motion if given."""
    act = lambda x: nnx.leaky_relu(x, 0.2)
    f = act(self.fuse(jnp.concatenate(parts[:3], -1)))
    if self.density_cells is None:
      return f, None
    f_v, f_i, f_t = parts[:3]
    return f, act(self.density_fuse(jnp.concatenate([jax.lax.stop_gradient(f_v), f_i, f_t]
                                                    + parts[3:], -1)))

  def _run_cells(self, cells, carry, x, train, rngs):
    new = []
    for i, (cell, state) in enumerate(zip(cells, carry)):
      if i > 0:
        x = self.dropout(x, deterministic=not train, rngs=rngs)
      state, x = cell(state, x)
      new.append(state)
    return new, x

  def _step(self, carry, prev, feats, train, rngs):
    """One generator step: (new carry, (density logits, half size, centre, quaternion)).

    Without a density branch (the paper's generator) one LSTM stack's output feeds all
    four heads. With one (`model.density_branch`), that stack feeds the geometry heads
    and a second stack the density head (slots and the end token); the second reads the
    fed-back primitive, its own features (`_fused`) and the first stack's output with its
    gradient stopped (which box this step describes). The density loss then reaches
    neither the geometry's LSTMs nor the voxel encoder: on tools the joint stage's density
    loss otherwise undid geometry (validation F1 63 -> 10 in its first 50 steps,
    docs/data.md), and the geometry loss does not bend the density branch.
    """
    f, f_d = feats
    n = len(self.cells)
    new, x = self._run_cells(self.cells, carry[:n], jnp.concatenate([prev, f], -1), train,
                             rngs)
    s = nnx.sigmoid(self.size_head(x)) * SIZE_SCALE
    t = jnp.tanh(self.trans_head(x)) * TRANS_SCALE
    r = self.rot_head(x)
    r = r / jnp.maximum(jnp.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
    if self.density_cells is not None:
      new_d, x = self._run_cells(
          self.density_cells, carry[n:],
          jnp.concatenate([prev, f_d, jax.lax.stop_gradient(x)], -1), train, rngs)
      new = new + new_d
    return new, (self.density_head(x), s, t, r)

  def _init_carry(self, b):
    z = jnp.zeros((b, self.hidden))
    return [(z, z) for _ in list(self.cells) + list(self.density_cells or [])]

  def __call__(self, obs: dict, prev_BSx112: jax.Array, train: bool = False,
               rngs=None) -> Prediction:
    """Teacher-forced pass: step s is fed `prev[:, s]` (the start token, then the truth)."""
    feats = self._fused(self._encoder_features(obs, train, rngs))
    carry, outs = self._init_carry(prev_BSx112.shape[0]), []
    for s in range(prev_BSx112.shape[1]):
      carry, out = self._step(carry, prev_BSx112[:, s], feats, train, rngs)
      outs.append(out)
    return Prediction(*[jnp.stack(o, 1) for o in zip(*outs)])

  def decode(self, obs: dict) -> tuple[Primitives, Prediction]:
    """Autoregressive inference (eval mode): until the end token or max_primitives boxes.

    Returns:
      (Primitives (B, K) with densities at the arg-max slot and a valid mask, the raw
      Prediction (B, K + 1, ...)). The first step always yields a box.
    """
    feats = self._fused(self._encoder_features(obs, False, None))
    b, k = feats[0].shape[0], self.max_primitives
    carry, outs = self._init_carry(b), []
    prev = primitive_vector(jnp.full((b,), START), jnp.zeros((b, 3)), jnp.zeros((b, 3)),
                            jnp.zeros((b, 4)))
    for _ in range(k + 1):
      carry, out = self._step(carry, prev, feats, False, None)
      outs.append(out)
      token = jnp.argmax(out[0].at[..., START].set(-jnp.inf), -1)
      prev = primitive_vector(token, *out[1:])
    pred = Prediction(*[jnp.stack(o, 1) for o in zip(*outs)])
    tokens = jnp.argmax(pred.density_logits[:, :k], -1)
    ended = jnp.cumsum(tokens == END, axis=1) > 0
    valid = (~ended).at[:, 0].set(True)
    slots = jnp.argmax(pred.density_logits[:, :k, :NUM_DENSITY_SLOTS], -1)
    prims = Primitives(pred.half_size[:, :k], pred.pos[:, :k], pred.quat[:, :k],
                       slot_to_density_jax(slots), valid)
    return prims, pred


# On a CPU the initial draw is compiled without LLVM's optimisations: it runs once, so its
# compile time is all it costs (the same draws; a few float transforms round differently).
CPU_INIT_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


def init_module(make: Callable[[], nnx.Module]) -> nnx.Module:
  """`make()`, its parameters drawn in one compiled program (eagerly, each parameter's
  shape would compile its own random draw: seconds per module on a CPU)."""
  graphdef = nnx.graphdef(nnx.eval_shape(make))
  options = CPU_INIT_COMPILER_OPTIONS if jax.default_backend() == "cpu" else None
  state = jax.jit(lambda: nnx.state(make())).lower().compile(options)()
  return nnx.merge(graphdef, state)


def init_ppd(config: ml_collections.ConfigDict, seed: int = 0) -> PPD:
  """A PPD of `config` (the model section), its parameters drawn from `seed`."""
  return init_module(lambda: PPD(config, rngs=nnx.Rngs(params=seed)))
