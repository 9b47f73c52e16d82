"""The box-plane rollout as one Pallas kernel: every step of a block of rollouts on chip.

`ppdjax.sim.box_plane` is the reference: array expressions that XLA runs as about 70
kernels per step, each writing its intermediates to memory. Here the same physics is one
GPU kernel per call (`BoxPlaneSettings(kernel="pallas")`): a program takes a block of
rollouts (`launch_shape`), keeps their state, contacts and constraint rows on chip and
loops over all steps, so a step costs no launches and no memory traffic beyond the poses
it writes.

The step itself is `box_plane_lanes.step` (`box_plane.step`'s physics, one lane per
rollout, contacts as tensors), small enough to compile in about 80-100 s;
tests/test_physics.py holds the kernel to the reference step's trajectories. Every
rollout under any number of `vmap`s is one launch (`jax.custom_batching.custom_vmap`).
Forward only: derivatives (`jax.jvp`, `jax.grad`) run the reference step
(`jax.custom_jvp`). Measured on one H100 (docs/physics.md, benchmarks.md): 0.001 mm from
the reference at p90 after 256 steps; 2,048 rollouts of 256 steps in 29 ms, 131,072 in
0.56 s (the XLA reference: 48 ms and 0.94 s).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from ppdjax.sim import box_plane
from ppdjax.sim.box_plane import CORNER_SIGNS, Body, BoxPlaneSettings
from ppdjax.sim.box_plane_lanes import CANDIDATES, step

# The launch: rollouts and GPU warps per program, by the number of rollouts. Measured on
# one H100 (experiments/benchmarks/kernel_sweep.py, benchmarks.md): at 2,048 rollouts 32 x 2 was the
# fastest of eight shapes (1.09x the 32 x 4 used before; larger blocks leave SMs idle), at
# 131,072 128 x 8 (1.69x; 32 x 2 1.48x): a program's steps are a long chain of dependent
# small operations, and more rollouts per program share that chain once many programs
# already fill the chip.
SMALL_LAUNCH = (32, 2)
LARGE_LAUNCH = (128, 8)
LARGE_FROM = 16384  # rollouts: 128 programs of 128, about one per streaming multiprocessor


def launch_shape(settings: BoxPlaneSettings, rollouts: int) -> tuple[int, int]:
  """(rollouts per program, warps per program) of a launch of `rollouts`: the settings'
  `kernel_block` and `kernel_warps` where set, else SMALL_LAUNCH's or LARGE_LAUNCH's."""
  block, warps = LARGE_LAUNCH if rollouts >= LARGE_FROM else SMALL_LAUNCH
  return settings.kernel_block or block, settings.kernel_warps or warps


# --- packing and the kernel ---------------------------------------------------------------

def _layout(k: int) -> dict[str, tuple]:
  """Rows of the packed input per field: name -> (first row, shape); candidate fields
  (4 per box: its centre and one corner of each opposite pair, body frame) end in
  CANDIDATES."""
  if 4 * k > CANDIDATES:
    raise ValueError(f"the kernel takes at most {CANDIDATES // 4} boxes, got {k}")
  shapes = {"mass": (), "com": (3,), "inertia": (3, 3), "qpos0": (7,), "wrench": (6,),
            "cand_pos": (3, CANDIDATES), "cand_corner": (3, CANDIDATES),
            "cand_valid": (CANDIDATES,)}
  out, row = {}, 0
  for name, shape in shapes.items():
    out[name] = (row, shape)
    row += math.prod(shape)
  return out


def _pack(body: Body, qpos0, wrench) -> jax.Array:
  """(F, N) rows of N rollouts' inputs (leading axes flattened), float32."""
  local = CORNER_SIGNS[None, :4] * body.half_size[..., None, :]  # (..., K, 4, 3)
  corner = jnp.einsum("...kij,...knj->...kni", body.box_rot, local)
  lead, k = qpos0.shape[:-1], body.valid.shape[-1]

  def candidates(x):  # (..., K, 4, m) -> (..., m * CANDIDATES), field-major
    x = x.reshape(lead + (4 * k, -1))
    x = jnp.pad(x, [(0, 0)] * len(lead) + [(0, CANDIDATES - 4 * k), (0, 0)])
    return jnp.swapaxes(x, -1, -2)

  per_box = lambda x: jnp.broadcast_to(x[..., :, None, :], lead + (k, 4, x.shape[-1]))
  fields = [body.mass, body.com, body.inertia, qpos0, wrench,
            candidates(per_box(body.box_pos)), candidates(corner),
            candidates(per_box(body.valid[..., None].astype(jnp.float32)))]
  cols = [jnp.asarray(x, jnp.float32).reshape(lead + (-1,)) for x in fields]
  return jnp.concatenate(cols, -1).reshape(-1, sum(c.shape[-1] for c in cols)).T


def _unpack(rows, layout):
  """A block's fields: scalars as (block,) arrays in nested tuples, candidate fields as
  (CANDIDATES, block) tensors (`rows` a ref or an array)."""
  def nest(start, shape):
    if shape == (CANDIDATES,):
      return rows[pl.ds(start, CANDIDATES), :]
    if not shape:
      return rows[start, :]
    size = math.prod(shape[1:])
    return tuple(nest(start + i * size, shape[1:]) for i in range(shape[0]))
  out = {name: nest(start, shape) for name, (start, shape) in layout.items()}
  out["cand_valid"] = out["cand_valid"] > 0.5
  return out


def _kernel(in_ref, out_ref, *, layout, num_candidates, steps, duration, n_push, settings):
  fields = dict(_unpack(in_ref, layout), num_candidates=num_candidates)
  zero = jnp.zeros_like(fields["mass"])
  state = (fields["qpos0"], (zero,) * 6, (zero,) * 6)

  def one(t, state):  # one loop for all steps keeps the kernel small: the push steps
    push = t < n_push  # differ only in their iteration counts
    extra = push.astype(jnp.int32)  # (arithmetic: a scalar `where` of ints lowers to a bool)
    iterations = settings.iterations + (settings.push_iterations - settings.iterations) * extra
    ls_iterations = (settings.ls_iterations
                     + (settings.push_ls_iterations - settings.ls_iterations) * extra)
    wrench = tuple(jnp.where(t < duration, w, 0.0) for w in fields["wrench"])
    state = step(fields, *state, wrench, iterations, ls_iterations, settings.max_contacts)
    for i in range(7):
      out_ref[t * 8 + i, :] = state[0][i]
    return state

  jax.lax.fori_loop(0, steps, one, state)


def _fused(body: Body, qpos0, wrench, *, steps, duration, settings, interpret):
  """(..., steps, 7) poses of rollouts with any leading axes, one kernel launch."""
  lead = qpos0.shape[:-1]
  packed = _pack(body, qpos0, wrench)
  n = packed.shape[1]
  block, warps = launch_shape(settings, n)
  n_pad = -(-n // block) * block
  layout = _layout(body.valid.shape[-1])
  rows = 1 << (packed.shape[0] - 1).bit_length()  # power-of-two blocks
  filler = np.zeros(packed.shape[0], np.float32)  # padding rollouts: a unit body, no boxes
  filler[[layout["mass"][0], layout["qpos0"][0] + 3]] = 1.0
  filler[layout["inertia"][0] + np.array([0, 4, 8])] = 1.0
  packed = jnp.concatenate([packed, jnp.broadcast_to(filler[:, None], (len(filler), n_pad - n))], 1)
  packed = jnp.pad(packed, ((0, rows - packed.shape[0]), (0, 0)))
  kernel = functools.partial(_kernel, layout=layout, num_candidates=4 * body.valid.shape[-1],
                             steps=steps,
                             duration=duration, settings=settings,
                             n_push=min(steps, duration + settings.push_steps_extra))
  out_rows = 1 << (steps * 8 - 1).bit_length()  # power-of-two blocks
  out = pl.pallas_call(
      kernel, out_shape=jax.ShapeDtypeStruct((out_rows, n_pad), jnp.float32),
      grid=(n_pad // block,), in_specs=[pl.BlockSpec((rows, block), lambda i: (0, i))],
      out_specs=pl.BlockSpec((out_rows, block), lambda i: (0, i)),
      compiler_params=_compiler_params(warps), interpret=interpret,
      name="box_plane_rollout",
  )(packed)
  poses = out[:steps * 8].reshape(steps, 8, n_pad)[:, :7, :n]
  return poses.transpose(2, 0, 1).reshape(lead + (steps, 7))


def _compiler_params(warps: int):
  from jax.experimental.pallas import triton as pl_triton  # GPU only
  return pl_triton.CompilerParams(num_warps=warps, num_stages=1)


@functools.lru_cache(maxsize=16)
def _batched(steps: int, duration: int, settings: BoxPlaneSettings, interpret: bool):
  """The kernel behind `jax.custom_batching.custom_vmap`: however many `vmap`s wrap a
  rollout (pushes, candidates, objects), they all become rows of one launch."""

  @jax.custom_batching.custom_vmap
  def run(body, qpos0, wrench):
    return _fused(body, qpos0, wrench, steps=steps, duration=duration, settings=settings,
                  interpret=interpret)

  @run.def_vmap
  def rule(axis_size, in_batched, body, qpos0, wrench):
    grow = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
    args = jax.tree.map(grow, (body, qpos0, wrench), tuple(in_batched))
    return run(*args), True

  return run


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _rollout(steps, duration, settings, interpret, body, qpos0, wrench):
  return _batched(steps, duration, settings, interpret)(body, qpos0, wrench)


@_rollout.defjvp
def _rollout_jvp(steps, duration, settings, interpret, primals, tangents):
  reference = functools.partial(box_plane.rollout, steps=steps, duration=duration,
                                settings=settings)
  return jax.jvp(reference, primals, tangents)


def rollout(body: Body, qpos0: jax.Array, wrench: jax.Array, *, steps: int, duration: int,
            settings: BoxPlaneSettings) -> jax.Array:
  """`box_plane.rollout`'s contract, (steps, 7) poses of one push, run by the kernel.

  Batch it with `jax.vmap` (any depth): the whole batch is one kernel launch.
  Derivatives run the reference step. Off a GPU the kernel is interpreted (slow: tests).
  """
  interpret = jax.default_backend() != "gpu"
  return _rollout(steps, duration, settings, interpret, body, qpos0, wrench)

