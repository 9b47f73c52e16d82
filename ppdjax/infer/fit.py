"""Test-time fit of oriented boxes to 32^3 voxels: the exact tower reading, then refinement.

`read_tower` (`tower_reading.py`) reads axis-aligned towers exactly. `fit_boxes`: Adam on
a soft occupancy of voxel centres (the voxelizer's separating-axis test on the 3 box and
3 world axes, each sigmoid((radius + voxel radius - |distance|) / T),
joined by 1 - prod(1 - occ)), class-balanced cross-entropy on sampled voxels, T annealed
from 1 to 0.05 voxel; the winner is chosen by the exact voxelization (`_select`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ppdjax.conventions import NUM_SLOTS, VOXEL_RESOLUTION as R
from ppdjax.dataset import voxels as voxelizer
from ppdjax.infer import depth_fit, faces, image_fit
from ppdjax.infer.tower_reading import (IDENTITY, VOXEL, as_bool, check_voxels, finish_boxes,
                                        read_one, read_tower)
from ppdjax.primitives import Primitives, flatten, mat_to_quat, quat_to_mat, unflatten

_ROT_SCALE = 8.0  # rotation columns scale like a point this many voxels from the centre
_SIZE_SCALE = 5.0  # log half sizes scale so that one Adam rate moves faces ~ like centres
__all__ = ["check_voxels", "fit_boxes", "read_tower"]


def _rotation(rot_Kx2x3: jax.Array) -> jax.Array:
  """(K, 3, 3) rotations (columns = box axes) from two 3-vectors per box (Gram-Schmidt)."""
  a, b = rot_Kx2x3[:, 0], rot_Kx2x3[:, 1]
  b1 = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
  b2 = b - jnp.sum(b1 * b, -1, keepdims=True) * b1
  b2 = b2 / jnp.linalg.norm(b2, axis=-1, keepdims=True)
  return jnp.stack([b1, b2, jnp.cross(b1, b2)], -1)


def _params(pos, half, rot) -> dict:
  """Optimiser parameters (voxel units, scaled for one Adam rate), kept in range."""
  lim = np.log([1e-3 / VOXEL, 0.5 / VOXEL])
  return {"pos": jnp.clip(pos, -0.5 / VOXEL, 0.5 / VOXEL),
          "logh": _SIZE_SCALE * jnp.clip(jnp.log(half), lim[0], lim[1]),
          "rot": _ROT_SCALE * jnp.swapaxes(rot[:, :, :2], 1, 2)}


def _to_params(prims: Primitives) -> dict:
  norm = jnp.linalg.norm(prims.quat, axis=-1, keepdims=True)
  quat = jnp.where(norm > 1e-6, prims.quat / jnp.maximum(norm, 1e-6), IDENTITY)
  return _params(prims.pos / VOXEL, jnp.maximum(prims.half_size, 1e-3) / VOXEL,
                 quat_to_mat(quat))


def _unpack(p: dict):
  """(centres, half sizes) in voxels and rotations of parameters."""
  return p["pos"], jnp.exp(p["logh"] / _SIZE_SCALE), _rotation(p["rot"])


def _to_prims(p: dict, valid: jax.Array) -> Primitives:
  pos, half, rot = _unpack(p)
  return finish_boxes(half * VOXEL, pos * VOXEL, jax.vmap(mat_to_quat)(rot), valid)


def _soft_loss(p: dict, valid, pts_Px3, filled_P, temp):
  """Class-balanced cross-entropy of the soft union of boxes at points (voxel units)."""
  pos, h, rot = _unpack(p)
  d = pts_Px3[:, None, :] - pos  # (P, K, 3)
  local = jnp.abs(jnp.einsum("pkj,kji->pki", d, rot))
  a_box = h + 0.5 * jnp.abs(rot).sum(1) - local  # box axes; voxel radius as margin
  a_world = jnp.einsum("kji,ki->kj", jnp.abs(rot), h) + 0.5 - jnp.abs(d)  # world axes
  occ = jnp.prod(jax.nn.sigmoid(jnp.concatenate([a_box, a_world], -1) / temp), -1)  # (P, K)
  log_none = jnp.where(valid, jnp.log1p(-jnp.minimum(occ, 1 - 1e-6)), 0.0).sum(-1)
  log_u = jnp.log(jnp.maximum(-jnp.expm1(log_none), 1e-30))
  return (-jnp.where(filled_P, log_u, 0.0).sum() / jnp.maximum(filled_P.sum(), 1)
          - jnp.where(filled_P, 0.0, log_none).sum() / jnp.maximum((~filled_P).sum(), 1))


def _sampler(vox_XYZ: jax.Array) -> jax.Array:
  """(V,) CDF over voxels: 3/4 of the mass on the surface band (either side of a face)."""
  v = jnp.pad(vox_XYZ, 1)
  band = jnp.zeros_like(vox_XYZ)
  for axis in range(3):
    for d in (-1, 1):
      band = band | (jnp.roll(v, d, axis) != v)[1:-1, 1:-1, 1:-1]
  band = band.reshape(-1).astype(jnp.float32)
  return jnp.cumsum(0.75 * band / jnp.maximum(band.sum(), 1.0) + 0.25 / band.size)


def _draw(cdf, key, n: int):
  """(points (n, 3) in voxels, their voxel indices) drawn from `cdf`."""
  idx = jnp.minimum(jnp.searchsorted(cdf, jax.random.uniform(key, (n,)) * cdf[-1]), R ** 3 - 1)
  return jnp.asarray(voxelizer.voxel_centers(R).reshape(-1, 3) / VOXEL)[idx], idx


def _refine(p: dict, valid, vox_XYZ, cdf, key, *, steps: int, points: int, lr: float) -> dict:
  """`steps` Adam steps on the soft loss, temperature 1 -> 0.05 voxel."""
  opt = optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05))
  labels = vox_XYZ.reshape(-1)

  def step(carry, inp):
    p, state = carry
    temp, k = inp
    pts, idx = _draw(cdf, k, points)
    grads = jax.grad(_soft_loss)(p, valid, pts, labels[idx], temp)
    updates, state = opt.update(grads, state, p)
    p = optax.apply_updates(p, updates)
    return (_params(p["pos"], *_unpack(p)[1:]), state), None

  temps = jnp.exp(jnp.linspace(0.0, np.log(0.05), steps))
  (p, _), _ = jax.lax.scan(step, (p, opt.init(p)), (temps, jax.random.split(key, steps)))
  return p


def _jitter(p: dict, key, scale: float, angle: float) -> dict:
  """Centres and half sizes moved by N(0, scale) voxels, turned by N(0, angle) per axis."""
  k1, k2, k3 = jax.random.split(key, 3)
  pos, h, rot = _unpack(p)
  rotvec = angle * jax.random.normal(k3, pos.shape)
  th = jnp.linalg.norm(rotvec, axis=-1, keepdims=True)
  q = jnp.concatenate([jnp.cos(th / 2), jnp.sin(th / 2) * rotvec / jnp.maximum(th, 1e-9)], -1)
  return _params(pos + scale * jax.random.normal(k1, pos.shape),
                 jnp.maximum(h + scale * jax.random.normal(k2, h.shape), 0.5),
                 quat_to_mat(q) @ rot)


def _box_occupancy(prims: Primitives) -> jax.Array:
  """(V, K) whether each voxel shares volume with each box of one object.

  The voxelizer's rule (`ppdjax.dataset.voxels`: separating axes, 3 voxel, 3 box and 9
  cross products), per box; grid projections are sums of per-axis terms.
  """
  c = jnp.asarray(voxelizer.voxel_centers(R)[:, 0, 0, 0])  # (R,) centres along an axis
  rot = quat_to_mat(prims.quat)  # (K, 3, 3)
  world = jnp.broadcast_to(jnp.eye(3), rot.shape)
  box = jnp.swapaxes(rot, 1, 2)
  cross = jnp.cross(world[:, :, None, :], box[:, None, :, :]).reshape(-1, 9, 3)
  axes = jnp.concatenate([world, box, cross], 1)  # (K, 15, 3)
  norm = jnp.linalg.norm(axes, axis=-1, keepdims=True)
  axes = jnp.where(norm > 1e-6, axes / jnp.maximum(norm, 1e-6), 0.0)
  r_box = (jnp.abs(jnp.einsum("kai,kij->kaj", axes, rot)) * prims.half_size[:, None]).sum(-1)
  touch = voxelizer.TOUCH
  lim = jnp.where(norm[..., 0] > 1e-6, VOXEL / 2 * jnp.abs(axes).sum(-1) + r_box - touch, jnp.inf)
  p = axes[..., None] * (c - prims.pos[:, None, :, None])  # (K, 15, 3, R)
  d = p[..., 0, :, None, None] + p[..., 1, None, :, None] + p[..., 2, None, None, :]
  inside = jnp.all(jnp.abs(d) < lim[..., None, None, None], axis=1)  # (K, R, R, R)
  return inside.reshape(-1, R ** 3).T & prims.valid


def _drop_sets(k: int) -> np.ndarray:
  """(1 + k + k(k-1)/2, k) 0/1 rows: drop nothing, each box, each pair of boxes."""
  eye = np.eye(k, dtype=np.int32)
  pairs = [eye[i] + eye[j] for i in range(k) for j in range(i + 1, k)]
  return np.concatenate([np.zeros((1, k), np.int32), eye, np.array(pairs, np.int32)])


def _select(cands: Primitives, soft_C, vox_XYZ, box_cost: float) -> Primitives:
  """The candidate (C, K), less at most two of its boxes, that best explains the voxels.

  Score: voxels where its exact voxelization and the input disagree, plus `box_cost` x
  (filled voxels) per box; an exact explanation scores 0 whatever its box count. Ties go
  to the lower `soft_C`.
  """
  k, filled = cands.valid.shape[-1], vox_XYZ.reshape(-1)
  drop = _drop_sets(k)  # (D, K)
  # voxels by the set of boxes covering them (a bit mask): dropping the boxes of d
  # uncovers exactly the voxels whose mask is a non-empty subset of d
  bits = jax.vmap(_box_occupancy)(cands).astype(jnp.int32) @ (2 ** jnp.arange(k))  # (C, V)
  gain = jax.vmap(lambda b: jnp.zeros(2 ** k, jnp.int32).at[b].add(
      jnp.where(filled, 1, -1)))(bits)  # (C, 2^K) filled minus empty voxels per mask
  masks, d_bits = np.arange(2 ** k), drop @ (2 ** np.arange(k))
  subset = ((masks & ~d_bits[:, None]) == 0) & (masks > 0)  # (D, 2^K)
  miss = jnp.sum((bits > 0) != filled, -1)[:, None] + gain @ subset.T.astype(np.int32)
  n = cands.valid.sum(-1)[:, None] - drop.sum(-1)  # boxes left, (C, D)
  ok = ~jnp.any((drop > 0) & ~cands.valid[:, None], -1) & (n > 0)
  score = jnp.where(miss == 0, 0.0, miss + box_cost * filled.sum() * n)
  score = jnp.where(ok, score, jnp.inf).reshape(-1)
  best = jnp.lexsort((jnp.repeat(soft_C, drop.shape[0]), score))[0]
  c, d = best // drop.shape[0], best % drop.shape[0]
  win = jax.tree.map(lambda x: x[c], cands)
  return finish_boxes(win.half_size, win.pos, win.quat, win.valid & (jnp.asarray(drop)[d] == 0))


def _explains(prims: Primitives, vox_XYZ) -> jax.Array:
  """Whether the exact voxelization of one object's boxes is the grid, voxel for voxel."""
  return ~jnp.any(_box_occupancy(prims).any(-1) != vox_XYZ.reshape(-1))


def _as_selected(reading: Primitives) -> Primitives:
  """A reading as `_select` returns it when it wins with no box dropped."""
  return finish_boxes(reading.half_size, reading.pos, reading.quat, reading.valid)


def _moments_box(vox_XYZ) -> Primitives:
  """One box with the filled voxels' mean and covariance (a box's variance is h^2 / 3)."""
  w = vox_XYZ.reshape(-1).astype(jnp.float32)
  pts = jnp.asarray(voxelizer.voxel_centers(R).reshape(-1, 3))
  mean = w @ pts / jnp.maximum(w.sum(), 1.0)
  d = pts - mean
  evals, rot = jnp.linalg.eigh((w[:, None] * d).T @ d / jnp.maximum(w.sum(), 1.0))
  rot = rot.at[:, 2].multiply(jnp.sign(jnp.linalg.det(rot)))  # a rotation, not a reflection
  first = jnp.arange(NUM_SLOTS) == 0
  return Primitives(jnp.where(first[:, None], jnp.sqrt(3 * jnp.maximum(evals, 1e-6)), 0.01),
                    jnp.where(first[:, None], mean, 0.0),
                    jnp.broadcast_to(mat_to_quat(rot), (NUM_SLOTS, 4)),
                    jnp.ones(NUM_SLOTS), first)


def _fit_one(vox_XYZ, init: Primitives | None, key, *, steps, points, lr, jitter_starts, jitter,
             jitter_angle, loose, box_cost) -> Primitives:
  """`fit_boxes` of one (R, R, R) bool grid."""
  bases = [read_one(vox_XYZ, NUM_SLOTS, loose), _moments_box(vox_XYZ)]
  bases += [] if init is None else [init]
  keys = jax.random.split(key, 2 + len(bases) * jitter_starts)
  starts, valids = [], []
  for b, base in enumerate(bases):
    p = _to_params(base)
    starts += [p] + [_jitter(p, keys[2 + b * jitter_starts + j], jitter, jitter_angle)
                     for j in range(jitter_starts)]
    valids += [base.valid] * (1 + jitter_starts)
  starts, valids = jax.tree.map(lambda *x: jnp.stack(x), *starts), jnp.stack(valids)
  cdf = _sampler(vox_XYZ)
  refine = functools.partial(_refine, vox_XYZ=vox_XYZ, cdf=cdf, steps=steps, points=points, lr=lr)
  refined = jax.vmap(refine)(starts, valids, key=jax.random.split(keys[0], len(valids)))
  reading = read_one(vox_XYZ, NUM_SLOTS)
  cands = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), reading,
                       jax.vmap(_to_prims)(refined, valids))
  pts, idx = _draw(cdf, keys[1], 4 * points)
  soft = jax.vmap(lambda c: _soft_loss(_to_params(c), c.valid, pts, vox_XYZ.reshape(-1)[idx],
                                       0.05))(cands)
  soft = soft.at[0].set(-jnp.inf)  # the exact reading wins ties (refined boxes may overlap)
  return _select(cands, soft, vox_XYZ, box_cost)


@functools.partial(jax.jit, static_argnames=("steps", "points", "lr", "jitter_starts", "jitter",
                                             "jitter_angle", "loose", "box_cost"))
def _fit_batch(vox_NxRxRxR, init: Primitives | None, seed, **options) -> Primitives:
  v = as_bool(vox_NxRxRxR)
  # the barrier keeps XLA from constant-folding every step's random key (slow to compile)
  keys = jax.random.split(jax.lax.optimization_barrier(jax.random.key(seed)), v.shape[0])
  one = functools.partial(_fit_one, **options)
  with jax.default_matmul_precision("highest"):  # the exact selection: no TF32 on GPUs
    readings = jax.vmap(lambda x: read_one(x, NUM_SLOTS))(v)
    exact = jax.vmap(_explains)(readings, v)
    if init is not None:
      init = jax.tree.map(lambda x: x if x.dtype == bool else x.astype(jnp.float32), init)

    def search():
      if init is None:
        return jax.vmap(lambda x, k: one(x, None, k))(v, keys)
      return jax.vmap(one)(v, init, keys)
    # An exact reading always wins `_select`, so when every grid of the batch has one
    # (axis-aligned towers) the refinement is skipped: same answer, no 200 Adam steps.
    return jax.lax.cond(jnp.all(exact), lambda: jax.vmap(_as_selected)(readings), search)


_snap_batch = jax.jit(jax.vmap(faces.snap_unit_extent))


def refine_fitted(boxes: Primitives, grids_NxRxRxR, *, image=None, depth=None,
                  camera: dict | None = None, depth_iterations: int = 15,
                  unit_extent: bool = True) -> Primitives:
  """A voxel fit's boxes (N, K) refined against the objects' images (N, H, W, 3), then
  their depth images (N, H, W), each where given (`fit_boxes` documents the steps; inputs
  unchecked: `fit_boxes` checks them), the unit-extent snap after each."""
  snap = _snap_batch if unit_extent else lambda p, v: p
  if image is not None:
    im = jnp.asarray(image)
    boxes = snap(image_fit.refine_batch(boxes, im.reshape((-1,) + im.shape[-3:]), camera),
                 grids_NxRxRxR)
  if depth is not None:
    d = jnp.asarray(depth, jnp.float32)
    boxes = snap(depth_fit.refine_batch(boxes, d.reshape((-1,) + d.shape[-2:]), camera,
                                        iterations=depth_iterations), grids_NxRxRxR)
  return boxes


def fit_boxes(voxels, init: Primitives | None = None, *, steps: int = 200, points: int = 256,
              lr: float = 0.1, jitter_starts: int = 0, jitter: float = 1.0,
              jitter_angle: float = 0.1, loose: float = 0.25, box_cost: float = 0.01,
              seed: int = 0, image=None, depth=None, camera: dict | None = None,
              depth_iterations: int = 15, unit_extent: bool = True) -> Primitives:
  """Fits up to K = 5 oriented boxes to voxel grids; jittable, batched over leading axes.

  When the exact tower reading explains every grid of the batch voxel for voxel, it is the
  answer and nothing else runs (its result is what the search would return). Otherwise,
  starts: a loose tower reading (slices alike at IoU >= 1 - `loose` form one run), one box
  with the voxels' moments, `init` if given, and `jitter_starts` jittered copies of each,
  all refined by `steps` Adam steps. Candidates: the exact `read_tower` reading and the
  refined starts, each also less any one or two boxes. The winner has the fewest voxels
  where its exact voxelization and the input disagree, plus `box_cost` x (filled voxels)
  per box; an exact explanation wins outright (ties: the exact reading, then the lower
  soft loss), so a tower's exact reading is never replaced. With an RGB `image` and its
  `camera`, the winner's faces are then moved within half a voxel to where their outline
  lies on the image's edges (`image_fit`). With a `depth` image and its `camera`, the
  faces are then refined against the depth (`depth_fit`): faces the camera sees become
  sub-voxel (with both, within half a voxel of the image fit's faces). Faces the camera does not see stay within half a voxel of the voxel fit.
  With `unit_extent` (objects normalised to a largest extent of 1 m, the project's
  convention), the faces that bound the object along the one axis that spans the grid go
  to ±0.5 m (`faces.snap_unit_extent`), before and after the image and depth refinements.
  Value checks run on concrete arrays only (under jit an empty grid gives no valid box).
  Under `jax.jit`, bind options (and the camera) with `functools.partial`.

  Args:
    voxels: (B..., 32, 32, 32) occupancy indexed [x, y, z]; bool, integer or 0/1 float.
    init: optional Primitives (B..., K) starting boxes (e.g. a network's prediction), 1..K
      valid boxes per object; densities are ignored.
    steps: Adam steps per start (the temperature anneals from 1 to 0.05 voxel over them).
    points: voxels sampled per step (3/4 from the input's surface band).
    lr: Adam's initial rate (about voxels per step), cosine decay to 5 %.
    jitter_starts: jittered copies of each start (0: none).
    jitter: standard deviation (voxels) of the jitter on centres and half sizes.
    jitter_angle: standard deviation (radians) of the jitter rotation, per axis.
    loose: IoU tolerance of the loose reading that seeds the refinement.
    box_cost: price of a box, as a fraction of the filled voxels (inexact candidates).
    seed: random seed (points drawn, jitter).
    image: optional (B..., H, W, 3) RGB images (uint8, or floats in [0, 1]) of the same
      objects at rest, as the dataset stores them (the network's input).
    depth: optional (B..., H, W) depth images (metres along the optical axis) of the same
      objects at rest, as the dataset stores them.
    camera: the images' camera (`storage.Dataset.camera`); required with `image` or `depth`.
    depth_iterations: Levenberg-Marquardt steps of the depth refinement.
    unit_extent: use the normalisation: the object's largest extent is 1 m (False: the
      voxels alone, for objects scaled otherwise).

  Returns:
    Primitives (B..., K): boxes bottom to top, canonical unit quats, density 1000
    (placeholder), padding last (half size 0, pos 0, identity quat, density 0).
  """
  batch = check_voxels(voxels, init)
  flat = None if init is None else flatten(jax.tree.map(jnp.asarray, init))[0]
  if flat is not None and flat.num_slots != NUM_SLOTS:
    raise ValueError(f"init: expected {NUM_SLOTS} slots, got {flat.num_slots}")
  if image is not None:
    image_fit.check_image(image, camera, batch)
  if depth is not None:
    depth_fit.check_depth(depth, camera, batch)
  if camera is not None and image is None and depth is None:
    raise ValueError("camera was given without an image or a depth image")
  grids = jnp.asarray(voxels).reshape(-1, R, R, R)
  out = _fit_batch(grids, flat, seed, steps=steps, points=points, lr=lr,
                   jitter_starts=jitter_starts, jitter=jitter, jitter_angle=jitter_angle,
                   loose=loose, box_cost=box_cost)
  snap = _snap_batch if unit_extent else lambda p, v: p
  out = refine_fitted(snap(out, grids), grids, image=image, depth=depth, camera=camera,
                      depth_iterations=depth_iterations, unit_extent=unit_extent)
  return unflatten(out, batch)
