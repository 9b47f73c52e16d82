"""Test-time fit of oriented boxes to a 32^3 occupancy grid: tower reading, then refinement.

Two readers, both jittable and batched over leading axes:

* `read_tower` reads an axis-aligned tower exactly from its z-profile. The voxelizer fills
  a voxel that shares volume with a box, so a z-slice is one block's rectangle, or, where
  an interface between two blocks falls inside the slice ("straddling" slice), the union
  of both rectangles. Pure slices in runs of identical masks are blocks; a straddling
  slice belongs to both neighbours. Faces go at the centre of the first/last occupied
  voxel along x and y, and along z at the centre of the first/last slice touching the
  block. Between two runs with no straddling slice the interface is placed by what the
  voxels allow: inside the slice of the block with the larger (containing) rectangle when
  the rectangles are nested, on the voxel boundary otherwise. Faces are within half a
  voxel of the truth for towers whose blocks are at least 2 voxels tall.
  Limitations: two stacked blocks with identical voxel rectangles form one run (one box
  for two: the count is off by one); with more than K = 5 runs the K largest (by voxel
  count) are kept; blocks thinner than 2 voxels may have no pure slice and be misread.
* `fit_boxes` refines several starts (the caller's `init`, the tower reading, jittered
  copies) by Adam on a soft occupancy of voxel centres, then keeps the candidate whose
  exact voxelization disagrees with the input on the fewest voxels (ties: the lower soft
  loss). The unrefined reading is always a candidate, so a tower is never made worse.

Soft occupancy of a voxel centre p for a box (c, h, R): the voxelizer's separating-axis
rule on the 3 box axes and the 3 world axes, each relaxed to a sigmoid,
  prod_i sigmoid((h_i + m_i - |R_i . (p - c)|) / T) * prod_j sigmoid((r_j + v/2 - |p_j - c_j|) / T),
with m_i = (v/2) sum_j |R_ji| the voxel's radius on box axis i, r_j = sum_i |R_ji| h_i the
box's radius on world axis j, and v the voxel size (axis-aligned boxes: exact at T -> 0).
Boxes are joined by a soft union 1 - prod_k (1 - occ_k) and scored by a class-balanced
binary cross-entropy at a temperature annealed from 1 to 0.05 voxel. Each step sees a
random sample of voxels, most near the input's surface, which keeps a step cheap.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ppdjax.conventions import NUM_SLOTS, VOXEL_RESOLUTION as R
from ppdjax.dataset import voxels as voxelizer
from ppdjax.primitives import (Primitives, bottom_to_top, canonical_boxes, flatten, mat_to_quat,
                               quat_to_mat, unflatten)

VOXEL = 1.0 / R  # m, one voxel
PLACEHOLDER_DENSITY = 1000.0  # kg/m^3 of the returned boxes; callers put densities on
_ROT_SCALE = 8.0  # voxels: a 6-D rotation column is scaled like a point at this lever arm
_SIZE_SCALE = 5.0  # log half sizes are scaled so that Adam's step is ~ a voxel fraction


# --- input checks ------------------------------------------------------------------------


def _is_concrete(x) -> bool:
  return not isinstance(x, jax.core.Tracer)


def check_voxels(voxels, init: Primitives | None = None) -> tuple[int, ...]:
  """Raises ValueError naming the problem; returns the batch shape of `voxels`."""
  shape, dtype = tuple(np.shape(voxels)), np.dtype(jnp.asarray(voxels).dtype)
  if len(shape) < 3 or shape[-3:] != (R, R, R):
    raise ValueError(f"voxels: expected shape (..., {R}, {R}, {R}), got {shape}")
  floating = np.issubdtype(dtype, np.floating)
  if not (dtype == np.bool_ or np.issubdtype(dtype, np.integer) or floating):
    raise ValueError(f"voxels: expected a bool, integer or 0/1 float dtype, got {dtype}")
  batch = shape[:-3]
  if _is_concrete(voxels):
    v = np.asarray(voxels)
    if dtype != np.bool_ and not np.all((v == 0) | (v == 1)):
      raise ValueError(f"voxels: values must be exactly 0 or 1 (binary occupancy), got "
                       f"dtype {dtype} with values in [{v.min()}, {v.max()}]")
    empty = ~v.reshape((-1, R ** 3)).astype(bool).any(-1)
    if empty.any():
      raise ValueError(f"voxels: {int(empty.sum())} of {empty.size} grids are all empty "
                       f"(first at flat index {int(np.argmax(empty))}); nothing to fit")
  elif floating:
    pass  # values of a traced float grid cannot be checked; they are thresholded at 0.5
  if init is not None and tuple(init.batch_shape) != batch:
    raise ValueError(f"init: batch shape {tuple(init.batch_shape)} does not match the "
                     f"voxels' batch shape {batch}")
  return batch


def _as_bool(voxels) -> jax.Array:
  v = jnp.asarray(voxels)
  return v > 0.5 if jnp.issubdtype(v.dtype, jnp.floating) else v != 0


# --- A. exact reading of axis-aligned towers ---------------------------------------------


def _center(i):
  """Centre (m) of voxel index i (float or int) along an axis."""
  return (i + 0.5) * VOXEL - 0.5


def _read_one(vox_XYZ: jax.Array, num_slots: int, tol: float = 0.0) -> Primitives:
  """`read_tower` for one (R, R, R) bool grid; masks count as equal at IoU >= 1 - tol."""
  s = jnp.moveaxis(vox_XYZ, -1, 0)  # (Z, X, Y) slices
  z = jnp.arange(R)
  none = jnp.zeros((1, R, R), bool)
  below, above = jnp.concatenate([none, s[:-1]]), jnp.concatenate([s[1:], none])
  inter = lambda a, b: jnp.sum(a & b, axis=(-2, -1))
  same = lambda a, b: inter(a, b) >= (1 - tol) * jnp.maximum(jnp.sum(a | b, axis=(-2, -1)), 1)
  subset = lambda a, b: jnp.all(~a | b, axis=(-2, -1))  # a within b
  occ = s.any((-2, -1))
  occ_below = jnp.concatenate([jnp.zeros(1, bool), occ[:-1]])
  occ_above = jnp.concatenate([occ[1:], jnp.zeros(1, bool)])
  # a straddling slice is the union of two different neighbours and equals neither
  straddle = (occ & occ_below & occ_above & same(s, below | above) & ~same(s, below)
              & ~same(s, above))
  pure = occ & ~straddle
  pure_below = jnp.concatenate([jnp.zeros(1, bool), pure[:-1]])
  start = pure & ~(pure_below & same(s, below))
  run = jnp.where(pure, jnp.cumsum(start) - 1, -1)  # (Z,) run index of each pure slice
  member = run[:, None] == jnp.arange(R)[None]  # (Z, runs)
  count = jnp.einsum("zr,z->r", member, s.sum((-2, -1)))
  lo = jnp.where(member, z[:, None], R).min(0)  # first / last pure slice of each run
  hi = jnp.where(member, z[:, None], -1).max(0)
  mask = jnp.einsum("zr,zxy->rxy", member.astype(jnp.int32), s.astype(jnp.int32)) > 0

  def face(end, step):
    """Face (m) of each run at its first (step -1) or last (step +1) pure slice `end`."""
    nb = jnp.clip(end + step, 0, R - 1)
    inside = (end + step >= 0) & (end + step < R)
    here, there = s[jnp.clip(end, 0, R - 1)], s[nb]
    centre_here, centre_there = _center(end.astype(jnp.float32)), _center(nb.astype(jnp.float32))
    boundary = centre_here + step * 0.5 * VOXEL
    # neighbouring pure run: the interface sits in the slice of the containing rectangle
    nested_out = subset(here, there)  # interface inside the neighbour's slice
    nested_in = subset(there, here)  # interface inside this run's own slice
    touching = jnp.where(nested_out, centre_there, jnp.where(nested_in, centre_here, boundary))
    return jnp.where(inside & straddle[nb], centre_there,
                     jnp.where(inside & pure[nb], touching, centre_here))

  z_lo, z_hi = face(lo, -1), face(hi, 1)
  x_any, y_any = mask.any(2), mask.any(1)  # (runs, X), (runs, Y)
  first = lambda m: jnp.argmax(m, -1)
  last = lambda m: R - 1 - jnp.argmax(m[:, ::-1], -1)
  x_lo, x_hi = _center(first(x_any)), _center(last(x_any))
  y_lo, y_hi = _center(first(y_any)), _center(last(y_any))
  lo3 = jnp.stack([x_lo, y_lo, z_lo], -1)
  hi3 = jnp.stack([x_hi, y_hi, z_hi], -1)
  # keep the num_slots largest runs
  _, keep = jax.lax.top_k(count, num_slots)
  valid = count[keep] > 0
  half = jnp.where(valid[:, None], (hi3[keep] - lo3[keep]) / 2, 0.0)
  pos = jnp.where(valid[:, None], (hi3[keep] + lo3[keep]) / 2, 0.0)
  return _finish(half, pos, jnp.broadcast_to(jnp.array([1.0, 0, 0, 0]), (num_slots, 4)), valid)


def _finish(half, pos, quat, valid) -> Primitives:
  """Primitives of one object, canonical labels, bottom to top, padding cleared."""
  prims = canonical_boxes(Primitives(half_size=half, pos=pos, quat=quat,
                                     density=jnp.full(valid.shape, PLACEHOLDER_DENSITY),
                                     valid=valid))
  prims = bottom_to_top(prims)
  v = prims.valid
  ident = jnp.array([1.0, 0.0, 0.0, 0.0])
  return Primitives(half_size=jnp.where(v[:, None], prims.half_size, 0.0),
                    pos=jnp.where(v[:, None], prims.pos, 0.0),
                    quat=jnp.where(v[:, None], prims.quat, ident),
                    density=jnp.where(v, PLACEHOLDER_DENSITY, 0.0), valid=v)


def read_tower(voxels, num_slots: int = NUM_SLOTS) -> Primitives:
  """Reads axis-aligned boxes from the z-profile of (B..., 32, 32, 32) voxel grids.

  Args:
    voxels: (B..., 32, 32, 32) occupancy indexed [x, y, z]; bool, integer or 0/1 float.
    num_slots: K, boxes per object (the largest runs are kept when there are more).

  Returns:
    Primitives (B..., K): axis-aligned boxes bottom to top, density 1000 (placeholder),
    padding last (half size 0, pos 0, identity quat). An empty grid gives no valid box.
  """
  batch = check_voxels(voxels)
  v = _as_bool(voxels).reshape((-1, R, R, R))
  return unflatten(jax.vmap(lambda x: _read_one(x, num_slots))(v), batch)


# --- B. differentiable refinement of oriented boxes ----------------------------------------


def _rotation(rot_Kx2x3: jax.Array) -> jax.Array:
  """(K, 3, 3) rotations (columns = box axes) from two 3-vectors per box (Gram-Schmidt)."""
  a, b = rot_Kx2x3[:, 0], rot_Kx2x3[:, 1]
  b1 = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
  b2 = b - jnp.sum(b1 * b, -1, keepdims=True) * b1
  b2 = b2 / jnp.linalg.norm(b2, axis=-1, keepdims=True)
  return jnp.stack([b1, b2, jnp.cross(b1, b2)], -1)


def _to_params(prims: Primitives) -> dict:
  """Optimiser parameters of one object's boxes (voxel units, scaled for one Adam rate)."""
  norm = jnp.linalg.norm(prims.quat, axis=-1, keepdims=True)
  quat = jnp.where(norm > 1e-6, prims.quat / jnp.maximum(norm, 1e-6), jnp.array([1.0, 0, 0, 0]))
  rot = jnp.swapaxes(quat_to_mat(quat)[:, :, :2], 1, 2)  # (K, 2, 3) first two axes
  half = jnp.clip(prims.half_size, 1e-3, 0.5) / VOXEL
  return {"pos": jnp.clip(prims.pos, -0.5, 0.5) / VOXEL,
          "logh": _SIZE_SCALE * jnp.log(half), "rot": _ROT_SCALE * rot}


def _project(params: dict) -> dict:
  """Keeps boxes in the unit cube, half sizes in [1e-3, 0.5] m, rotation columns orthonormal."""
  lim = np.log(np.float32([1e-3 / VOXEL, 0.5 / VOXEL])) * _SIZE_SCALE
  rot = jnp.swapaxes(_rotation(params["rot"])[:, :, :2], 1, 2)
  return {"pos": jnp.clip(params["pos"], -0.5 / VOXEL, 0.5 / VOXEL),
          "logh": jnp.clip(params["logh"], lim[0], lim[1]), "rot": _ROT_SCALE * rot}


def _to_prims(params: dict, valid: jax.Array) -> Primitives:
  rot = _rotation(params["rot"])
  half = jnp.clip(jnp.exp(params["logh"] / _SIZE_SCALE) * VOXEL, 1e-3, 0.5)
  return _finish(half, params["pos"] * VOXEL, jax.vmap(mat_to_quat)(rot), valid)


def _soft_logs(params: dict, valid: jax.Array, pts_Px3: jax.Array, temp):
  """(log u, log(1 - u)) of the soft union u at points (voxel units), each (P,)."""
  rot = _rotation(params["rot"])  # (K, 3, 3)
  h = jnp.exp(params["logh"] / _SIZE_SCALE)  # (K, 3) voxels
  d = pts_Px3[:, None, :] - params["pos"][None]  # (P, K, 3)
  local = jnp.einsum("pkj,kji->pki", d, rot)
  a_box = (h + 0.5 * jnp.abs(rot).sum(1) - jnp.abs(local)) / temp  # box axes
  a_world = (jnp.einsum("kji,ki->kj", jnp.abs(rot), h) + 0.5 - jnp.abs(d)) / temp  # world axes
  occ = jnp.prod(jax.nn.sigmoid(jnp.concatenate([a_box, a_world], -1)), -1)  # (P, K)
  log_none = jnp.where(valid, jnp.log1p(-jnp.minimum(occ, 1 - 1e-6)), 0.0).sum(-1)
  log_u = jnp.log(jnp.maximum(-jnp.expm1(log_none), 1e-30))
  return log_u, log_none


def _soft_loss(params, valid, pts_Px3, filled_P, temp):
  """Class-balanced binary cross-entropy of the soft union against labels at points."""
  log_u, log_none = _soft_logs(params, valid, pts_Px3, temp)
  n_filled = jnp.maximum(filled_P.sum(), 1)
  n_empty = jnp.maximum((~filled_P).sum(), 1)
  return (-jnp.where(filled_P, log_u, 0.0).sum() / n_filled
          - jnp.where(filled_P, 0.0, log_none).sum() / n_empty)


def _grid_points() -> np.ndarray:
  return voxelizer.voxel_centers(R).reshape(-1, 3) / VOXEL  # (V, 3) voxel units


def _sampler(vox_XYZ: jax.Array):
  """CDF over voxels for drawing points: 3/4 of the mass on the input's surface band."""
  v = jnp.pad(vox_XYZ, 1)
  core = v[1:-1, 1:-1, 1:-1]
  band = jnp.zeros_like(core)
  for axis in range(3):
    for shift in (-1, 1):
      band = band | (jnp.roll(v, shift, axis)[1:-1, 1:-1, 1:-1] != core)
  band = band.reshape(-1).astype(jnp.float32)
  prob = 0.75 * band / jnp.maximum(band.sum(), 1.0) + 0.25 / band.size
  return jnp.cumsum(prob)


def _refine(params: dict, valid, vox_XYZ, cdf, key, *, steps: int, points: int, lr: float):
  """Adam on the soft loss, temperature 1 -> 0.05 voxel, `points` sampled voxels per step."""
  grid, labels = jnp.asarray(_grid_points()), vox_XYZ.reshape(-1)
  opt = optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05))
  temps = jnp.exp(jnp.linspace(0.0, np.log(0.05), steps))

  def step(carry, inp):
    params, state = carry
    temp, k = inp
    idx = jnp.searchsorted(cdf, jax.random.uniform(k, (points,)) * cdf[-1])
    idx = jnp.minimum(idx, labels.size - 1)
    loss, grads = jax.value_and_grad(_soft_loss)(params, valid, grid[idx], labels[idx], temp)
    updates, state = opt.update(grads, state, params)
    return (_project(optax.apply_updates(params, updates)), state), loss

  (params, _), _ = jax.lax.scan(step, (params, opt.init(params)),
                                (temps, jax.random.split(key, steps)))
  return params


def _jitter(params: dict, key, scale: float, angle: float) -> dict:
  """Noisy copy: centres and half sizes by N(0, scale) voxels, a rotation of ~N(0, angle)."""
  k1, k2, k3 = jax.random.split(key, 3)
  h = jnp.exp(params["logh"] / _SIZE_SCALE)
  h = jnp.maximum(h + scale * jax.random.normal(k2, h.shape), 0.5)
  rotvec = angle * jax.random.normal(k3, h.shape)
  th = jnp.linalg.norm(rotvec, axis=-1, keepdims=True)
  q = jnp.concatenate([jnp.cos(th / 2), jnp.sin(th / 2) * rotvec / jnp.maximum(th, 1e-9)], -1)
  rot = jnp.einsum("kij,kjl->kil", quat_to_mat(q), _rotation(params["rot"]))
  return _project({"pos": params["pos"] + scale * jax.random.normal(k1, h.shape),
                   "logh": _SIZE_SCALE * jnp.log(h),
                   "rot": _ROT_SCALE * jnp.swapaxes(rot[:, :, :2], 1, 2)})


def _box_occupancy(prims: Primitives) -> jax.Array:
  """(V, K) whether each voxel shares volume with each box of one object.

  The voxelizer's rule (`ppdjax.dataset.voxels`: separating axes, 3 voxel, 3 box and 9
  cross products), per box; projections of the grid are sums of per-axis terms.
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
  lim = 0.5 * VOXEL * jnp.abs(axes).sum(-1) + r_box - voxelizer._TOUCH  # pylint: disable=protected-access
  lim = jnp.where(norm[..., 0] > 1e-6, lim, jnp.inf)  # parallel edges give no axis
  p = axes[..., None] * (c - prims.pos[:, None, :, None])  # (K, 15, 3, R)
  d = p[..., 0, :, None, None] + p[..., 1, None, :, None] + p[..., 2, None, None, :]
  inside = jnp.all(jnp.abs(d) < lim[..., None, None, None], axis=1)  # (K, R, R, R)
  return inside.reshape(-1, R ** 3).T & prims.valid


def _drop_sets(k: int) -> np.ndarray:
  """(1 + k + k(k-1)/2, k) 0/1 rows: drop nothing, each box, each pair of boxes."""
  rows = [np.zeros(k)] + [np.eye(k)[i] for i in range(k)]
  rows += [np.eye(k)[i] + np.eye(k)[j] for i in range(k) for j in range(i + 1, k)]
  return np.array(rows, np.int32)


def _select(cands: Primitives, soft_C, vox_XYZ, box_cost: float) -> Primitives:
  """The candidate (C, K), or it less one or two boxes, that best explains the voxels.

  Score: voxels where the exact voxelization disagrees with the input, plus `box_cost`
  times the filled-voxel count per box; 0 for an exact explanation, whatever its box count
  (ties: the lower soft loss, the exact reading first).
  """
  k = cands.valid.shape[-1]
  filled = vox_XYZ.reshape(-1)
  drop = jnp.asarray(_drop_sets(k))  # (D, K)
  # voxels by the set of boxes covering them (a bit mask); dropping the set d uncovers
  # exactly the voxels whose mask is a non-empty subset of d
  bits = jax.vmap(_box_occupancy)(cands).astype(jnp.int32) @ (2 ** jnp.arange(k))  # (C, V)
  sign = jnp.where(filled, 1, -1)
  gain = jax.vmap(lambda b: jnp.zeros(2 ** k, jnp.int32).at[b].add(sign))(bits)  # (C, 2^K)
  masks, d_bits = np.arange(2 ** k), _drop_sets(k) @ (2 ** np.arange(k))
  subset = jnp.asarray((masks[None] & ~d_bits[:, None]) == 0) & (masks[None] > 0)  # (D, 2^K)
  miss = jnp.sum((bits > 0) != filled, -1)[:, None] + gain @ subset.T.astype(jnp.int32)
  n = cands.valid.sum(-1)[:, None] - drop.sum(-1)  # boxes left, (C, D)
  ok = ~jnp.any(drop.astype(bool) & ~cands.valid[:, None], -1) & (n > 0)
  score = jnp.where(miss == 0, 0.0, miss + box_cost * filled.sum() * n)  # exact wins
  score = jnp.where(ok, score, jnp.inf)
  flat = jnp.lexsort((jnp.broadcast_to(soft_C[:, None], score.shape).reshape(-1),
                      score.reshape(-1)))[0]
  c, d = flat // score.shape[1], flat % score.shape[1]
  best = jax.tree.map(lambda x: x[c], cands)
  return _finish(best.half_size, best.pos, best.quat, best.valid & (drop[d] == 0))


def _fit_one(vox_XYZ, init: Primitives | None, key, *, steps, points, lr, jitter_starts, jitter,
             jitter_angle, loose, box_cost):
  """Best of the starts for one (R, R, R) bool grid; Primitives (K,)."""
  reading = _read_one(vox_XYZ, NUM_SLOTS)
  bases = [_read_one(vox_XYZ, NUM_SLOTS, loose)] + ([] if init is None else [init])
  starts, valids = [], []
  for b, base in enumerate(bases):
    p = _to_params(base)
    starts.append(p)
    valids.append(base.valid)
    for j in range(jitter_starts):
      starts.append(_jitter(p, jax.random.fold_in(key, 100 + 10 * b + j), jitter, jitter_angle))
      valids.append(base.valid)
  starts = jax.tree.map(lambda *x: jnp.stack(x), *starts)
  valids = jnp.stack(valids)
  cdf = _sampler(vox_XYZ)
  keys = jax.random.split(key, valids.shape[0] + 1)
  refined = jax.vmap(lambda p, v, k: _refine(p, v, vox_XYZ, cdf, k, steps=steps, points=points,
                                             lr=lr))(starts, valids, keys[1:])
  cands = jax.vmap(_to_prims)(refined, valids)
  cands = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), reading, cands)
  idx = jnp.searchsorted(cdf, jax.random.uniform(keys[0], (4 * points,)) * cdf[-1])
  idx = jnp.minimum(idx, R ** 3 - 1)
  pts, labels = jnp.asarray(_grid_points())[idx], vox_XYZ.reshape(-1)[idx]
  soft = jax.vmap(lambda c: _soft_loss(_to_params(c), c.valid, pts, labels, 0.05))(cands)
  soft = soft.at[0].set(-jnp.inf)  # the exact reading wins ties (refined boxes may overlap)
  return _select(cands, soft, vox_XYZ, box_cost)


def fit_boxes(voxels, init: Primitives | None = None, *, steps: int = 200, points: int = 256,
              lr: float = 0.1, jitter_starts: int = 0, jitter: float = 1.0,
              jitter_angle: float = 0.1, loose: float = 0.25, box_cost: float = 0.01,
              seed: int = 0) -> Primitives:
  """Fits up to K = 5 oriented boxes to (B..., 32, 32, 32) voxel grids; jittable, batched.

  Starts per object: a loose tower reading (slices alike at IoU >= 1 - `loose` form one
  run) and `init` if given, plus `jitter_starts` jittered copies of each, all refined by
  `steps` Adam steps. Candidates: the exact `read_tower` reading and the refined starts,
  each also with any one or two of its boxes dropped. The winner has the fewest voxels
  where its exact voxelization disagrees with the input, plus `box_cost` x (filled voxels)
  per box, an exact explanation winning outright (ties: the exact reading first, then the
  lower soft loss). Value checks (0/1 values, no empty grid) run on concrete arrays only;
  under jit an empty grid gives no valid box. Options are Python values: under `jax.jit`
  bind them with `functools.partial` (or `static_argnames`).

  Args:
    voxels: (B..., 32, 32, 32) occupancy indexed [x, y, z]; bool, integer or 0/1 float.
    init: optional Primitives (B..., K) starting boxes (e.g. a network's prediction), any
      number 1..K of valid boxes per object; densities are ignored.
    steps: Adam steps per start (the temperature anneals from 1 to 0.05 voxel over them).
    points: voxels sampled per step (3/4 from the input's surface band).
    lr: Adam's initial rate, about voxels per step (cosine decay to 5 %).
    jitter_starts: jittered copies of each start (0: none).
    jitter: standard deviation (voxels) of the jitter on centres and half sizes.
    jitter_angle: standard deviation (radians) of the jitter rotation, per axis.
    loose: IoU tolerance of the loose reading that seeds the refinement.
    box_cost: price of a box, as a fraction of the filled voxels (inexact candidates).
    seed: random seed for point sampling and jitter.

  Returns:
    Primitives (B..., K): boxes bottom to top, canonical unit quats, density 1000
    (placeholder), padding last (half size 0, pos 0, identity quat, density 0).
  """
  batch = check_voxels(voxels, init)
  v = _as_bool(voxels).reshape((-1, R, R, R))
  flat_init = None if init is None else flatten(jax.tree.map(jnp.asarray, init))[0]
  if flat_init is not None and flat_init.num_slots != NUM_SLOTS:
    raise ValueError(f"init: expected {NUM_SLOTS} slots, got {flat_init.num_slots}")
  keys = jax.random.split(jax.random.key(seed), v.shape[0])
  one = functools.partial(_fit_one, steps=steps, points=points, lr=lr,
                          jitter_starts=jitter_starts, jitter=jitter, jitter_angle=jitter_angle,
                          loose=loose, box_cost=box_cost)
  if flat_init is None:
    out = jax.vmap(lambda x, k: one(x, None, k))(v, keys)
  else:
    flat_init = flat_init.replace(half_size=flat_init.half_size.astype(jnp.float32),
                                  pos=flat_init.pos.astype(jnp.float32),
                                  quat=flat_init.quat.astype(jnp.float32))
    out = jax.vmap(one)(v, flat_init, keys)
  return unflatten(out, batch)
