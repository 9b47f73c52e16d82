"""Boxes fitted to voxels, refined against a depth image: faces the camera sees become
sub-voxel, faces it cannot see stay where the voxels put them.

Each box's six faces (lo and hi along its own axes) move within `bound` of where the voxel
fit put them (half a voxel: the voxelizer fills every voxel a box shares volume with, so a
face lies within half a voxel of the centre of its last filled voxel). Faces that touch in
the voxel fit (a block standing on another: one's top, the other's bottom) stay touching,
so a visible top carries the hidden bottom above it. Projected Levenberg-Marquardt over the
6K faces on `depth.residuals`, with forward-mode Jacobians (one batched call per step),
then a sweep (`sweep_faces`) that centres each face in the positions its pixels accept.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import VOXEL_RESOLUTION
from ppdjax.dataset.camera import check_camera
from ppdjax.dataset.depth import camera_rays
from ppdjax.infer import depth as depth_lib
from ppdjax.primitives import Primitives, quat_to_mat

VOXEL = 1.0 / VOXEL_RESOLUTION
TOUCHING = 1e-4  # m: faces this close in the voxel fit count as touching
TIE_WEIGHT = 30.0  # residual weight of a touching pair's gap (pixels weigh 1 each)
MIN_HALF = 1e-3  # m
CHUNK = 8  # objects refined together (224² pixels x 30 faces: about 2 GB per chunk)
ROBUST = 0.03  # m: pixel residuals well beyond this saturate (arctan; see refine_with_depth)
MISMATCH = 5e-4  # m: a pixel the boxes explain worse than this disagrees (`sweep_faces`)
SWEEP_COARSE = 33  # offsets over a face's whole interval, then
SWEEP_FINE = 9  # offsets across each end of its agreeing run (`sweep_faces`)


def boxes_from_faces(prims: Primitives, faces_Kx6) -> Primitives:
  """Boxes with their faces (lo, hi offsets from the start's centre along box axes),
  shifted along z so that the object's bounding box is centred (the object frame's
  convention: depth sees where the object stands, not where its frame's origin is)."""
  lo, hi = faces_Kx6[:, :3], faces_Kx6[:, 3:]
  rot = quat_to_mat(prims.quat)
  half = 0.5 * (hi - lo)
  pos = prims.pos + jnp.einsum("kij,kj->ki", rot, 0.5 * (hi + lo))
  reach = (jnp.abs(rot[:, 2, :]) * half).sum(-1)  # each box's half extent along z
  bottom = jnp.where(prims.valid, pos[:, 2] - reach, jnp.inf).min()
  top = jnp.where(prims.valid, pos[:, 2] + reach, -jnp.inf).max()
  return prims.replace(half_size=half, pos=pos.at[:, 2].add(-0.5 * (bottom + top)))


def touching_faces(prims: Primitives):
  """(K, K, 3) bool: box i's hi face touches box j's lo face along axis a (same rotation,
  overlapping across the other two axes), in the starting boxes."""
  rot = quat_to_mat(prims.quat)
  same = (jnp.abs(jnp.einsum("kab,jab->kj", rot, rot) - 3.0) < 1e-4)  # equal rotations
  c = jnp.einsum("kji,kj->ki", rot, prims.pos)  # centres along each box's own axes
  lo, hi = c - prims.half_size, c + prims.half_size
  touch = jnp.abs(hi[:, None, :] - lo[None, :, :]) < TOUCHING  # (i, j, a)
  overlap = (jnp.minimum(hi[:, None], hi[None]) > jnp.maximum(lo[:, None], lo[None]) + 1e-6)
  across = jnp.stack([overlap[..., (a + 1) % 3] & overlap[..., (a + 2) % 3]
                      for a in range(3)], -1)
  valid = prims.valid[:, None] & prims.valid[None, :]
  return touch & across & (same & valid)[..., None] & ~jnp.eye(len(lo), dtype=bool)[..., None]


def refine_batch(prims: Primitives, depth_BxHxW, camera: dict, *, iterations: int = 15,
                 sweep: bool = True, bound: float = VOXEL / 2) -> Primitives:
  """`refine_with_depth` over a batch (B, K) of objects seen by one camera (jitted once per
  image size, iteration count and bound; CHUNK objects at a time bound the Jacobians'
  memory)."""
  cam = check_camera(camera)
  return _refine_batch(prims, jnp.asarray(depth_BxHxW, jnp.float32),
                       jnp.asarray(cam["intrinsics"], jnp.float32),
                       jnp.asarray(cam["camera_from_world"], jnp.float32),
                       iterations=iterations, sweep=sweep, bound=float(bound))


@functools.partial(jax.jit, static_argnames=("iterations", "sweep", "bound"))
def _refine_batch(prims, depth_BxHxW, intrinsics, camera_from_world, iterations, sweep, bound):
  one = lambda p, d: refine_with_depth(p, d, intrinsics, camera_from_world, bound=bound,
                                       iterations=iterations, sweep=sweep)
  with jax.default_matmul_precision("highest"):  # GPUs' TF32 default: mm at 2.6 m
    return map_by_box_count(one, prims, depth_BxHxW, chunk=CHUNK)


def refine_with_depth(prims: Primitives, depth_HW, intrinsics, camera_from_world, *,
                      bound: float = VOXEL / 2, iterations: int = 15,
                      damping: float = 1e-3, sweep: bool = True) -> Primitives:
  """One object's boxes (K, object frame) refined against its depth image (H, W).

  Pixel residuals pass through ROBUST·arctan(r / ROBUST): a pixel where the rendering hits
  another box than the observation (a box's edge still a few millimetres short, so the ray
  goes on to a box behind) gives a large residual whose gradient moves the wrong box; the
  arctan makes such pixels count for little.

  LM stops at the first position a silhouette edge's pixels accept, up to a pixel's
  footprint from the face (several millimetres, and a face seen only by its edges, e.g.
  a back face through the top face's far edge, has nothing else). `sweep` then moves
  each face to the middle of the run of positions that every pixel accepts
  (`sweep_faces`): many pixels along a slanted edge pin it finer than one pixel.

  Args:
    prims: the voxel fit (`fit.fit_boxes`); rotations are kept.
    depth_HW: observed depth (metres along the optical axis), as the dataset stores it.
    intrinsics, camera_from_world: the dataset's camera (`storage.Dataset.camera`).
    bound: how far (m) a face may move from the start.
    iterations: Levenberg-Marquardt steps.
    damping: the starting Levenberg-Marquardt damping.
    sweep: then centre each face in the positions its pixels accept (`sweep_faces`).
  """
  h, w = depth_HW.shape
  origin, dirs = camera_rays(intrinsics, camera_from_world, h, w)
  obs = jnp.asarray(depth_HW, jnp.float32).reshape(-1)
  mask = depth_lib.mask_from_rays(obs, origin, dirs, camera_from_world)
  dirs = dirs.reshape(-1, 3)
  ties = touching_faces(prims)
  rot = quat_to_mat(prims.quat)
  centre_axes = jnp.einsum("kji,kj->ki", rot, prims.pos)
  start = jnp.concatenate([-prims.half_size, prims.half_size], -1)  # (K, 6)
  k = start.shape[0]

  def residual(x):
    faces = x.reshape(k, 6)
    boxes = boxes_from_faces(prims, faces)
    pix = depth_lib.residuals(boxes, obs, mask, origin, dirs)
    pix = ROBUST * jnp.arctan(pix / ROBUST)
    hi, lo = centre_axes + faces[:, 3:], centre_axes + faces[:, :3]
    gap = jnp.where(ties, hi[:, None, :] - lo[None, :, :], 0.0)
    return jnp.concatenate([pix, TIE_WEIGHT * gap.reshape(-1)])

  def project(x):
    faces = jnp.clip(x.reshape(k, 6), start - bound, start + bound)
    lo = jnp.minimum(faces[:, :3], faces[:, 3:] - 2 * MIN_HALF)
    return jnp.concatenate([lo, faces[:, 3:]], -1).reshape(-1)

  def step(carry, _):
    x, r, lam = carry
    jac = jax.jacfwd(residual)(x)
    jtj, g = jac.T @ jac, jac.T @ r
    a = jtj + lam * (jnp.diag(jnp.diag(jtj)) + 1e-6 * jnp.eye(x.size))
    new = project(x - jnp.linalg.solve(a, g))
    r_new = residual(new)
    better = jnp.sum(r_new * r_new) < jnp.sum(r * r)
    return (jnp.where(better, new, x), jnp.where(better, r_new, r),
            jnp.where(better, lam * 0.3, lam * 4.0)), None

  x0 = start.reshape(-1)
  (x, _, _), _ = jax.lax.scan(step, (x0, residual(x0), jnp.float32(damping)), None,
                              length=iterations)
  faces = x.reshape(k, 6)
  if sweep:
    mismatch = lambda f: jnp.sum(jnp.abs(depth_lib.residuals(boxes_from_faces(prims, f), obs, mask,
                                                             origin, dirs)) > MISMATCH)
    faces = sweep_faces(faces, start - bound, start + bound, ties, prims.valid, mismatch)
  out = boxes_from_faces(prims, faces)
  keep = prims.valid[:, None]
  return out.replace(half_size=jnp.where(keep, out.half_size, prims.half_size),
                     pos=jnp.where(keep, out.pos, prims.pos))


def _tied_offsets(face, ties_KxKx3):
  """(K, 6) 0/1: which faces move when face `face` (index into the flattened K x 6) moves:
  itself and the faces it touches (a hi face's touching lo faces, and back)."""
  k = ties_KxKx3.shape[0]
  box, col = face // 6, face % 6
  axis, is_hi = col % 3, col >= 3
  hi_partners = ties_KxKx3[box, :, axis]  # box's hi face touches these boxes' lo faces
  lo_partners = ties_KxKx3[:, box, axis]  # these boxes' hi faces touch box's lo face
  onehot = jax.nn.one_hot(axis, 3, dtype=jnp.float32)
  partner = jnp.where(is_hi, hi_partners, lo_partners)[:, None] * onehot[None]
  lo_move, hi_move = jnp.where(is_hi, partner, 0.0), jnp.where(is_hi, 0.0, partner)
  own = jax.nn.one_hot(face, 6 * k, dtype=jnp.float32).reshape(k, 6)
  return jnp.maximum(own, jnp.concatenate([lo_move, hi_move], -1))


def sweep_faces(faces_Kx6, lo_Kx6, hi_Kx6, ties_KxKx3, valid_K, mismatch, *,
                coarse_steps: int = SWEEP_COARSE, fine_steps: int = SWEEP_FINE,
                local=None):
  """Each valid face in turn moved to the middle of the run of positions within
  [lo, hi] where `mismatch(faces)` (pixels the boxes fail to explain) is least, touching
  faces moving with it: the run around the face's own position, or around the nearest
  coarse offset if one explains more pixels. A coarse scan of the interval finds the run
  (the face's own position counts: a face seen head-on agrees at one point only); a finer
  scan across each end places that end. A face no pixel sees keeps a flat count: it goes
  to the middle of its interval (the voxels' verdict). `coarse_steps` offsets span the
  interval, `fine_steps` each end's scan.

  `local(faces_a, faces_b, move)`, if given, returns the mismatch to use for one face's
  positions, from the faces at both ends of its sweep and which faces move (K, 6): one
  that leaves out what no position changes (`image_regions`); the positions' ranking
  must stay that of `mismatch`."""
  coarse = jnp.linspace(0.0, 1.0, coarse_steps)
  fine = jnp.linspace(0.0, 1.0, fine_steps)

  def one(faces, face):
    move = _tied_offsets(face, ties_KxKx3)
    lo, hi = lo_Kx6.reshape(-1)[face], hi_Kx6.reshape(-1)[face]
    now = faces.reshape(-1)[face]
    at = lambda value: faces + move * (value - now)
    if local is not None:
      score = local(at(jnp.minimum(lo, now)), at(jnp.maximum(hi, now)), move)
    else:
      score = mismatch
    counts = lambda values: jax.vmap(lambda v: score(at(v)))(values)
    grid = lo + (hi - lo) * coarse
    # one batch of scores for the coarse scan and the face's own position, one for both
    # ends' fine scans: two calls of `score` to compile per sweep, not four
    both = counts(jnp.append(grid, now))
    grid_counts, own = both[:-1], both[-1]
    # the anchor: the face itself, or the nearest coarse offset that explains more pixels
    nearest_best = grid[jnp.argmin(jnp.where(grid_counts == grid_counts.min(),
                                             jnp.abs(grid - now), jnp.inf))]
    least = jnp.minimum(own, grid_counts.min())
    anchor = jnp.where(grid_counts.min() < own, nearest_best, now)
    worse = grid_counts > least
    idx = jnp.arange(coarse_steps)

    def scan(side):  # side -1: the run's lower end, +1: its upper end
      ahead = side * (grid - anchor) > 0  # coarse offsets on this side of the anchor
      # the nearest worse coarse offset on this side
      block = -side * jnp.where(ahead & worse, -side * idx, -coarse_steps).max()
      found = (ahead & worse).any()
      inner_i = jnp.clip(block - side, 0, coarse_steps - 1)  # the last agreeing one before
      inner = jnp.where(found & (side * (grid[inner_i] - anchor) > 0), grid[inner_i], anchor)
      outer = grid[jnp.clip(block, 0, coarse_steps - 1)]
      return inner + (outer - inner) * fine, found

    (values_lo, found_lo), (values_hi, found_hi) = scan(-1), scan(1)
    fine_counts = counts(jnp.concatenate([values_lo, values_hi]))

    def end(side, values, found, fine_counts):
      agree = fine_counts <= least
      last = jnp.where(jnp.cumprod(agree) > 0, jnp.arange(fine_steps), 0).max()
      return jnp.where(found, values[last], jnp.where(side < 0, lo, hi))

    lower = end(-1, values_lo, found_lo, fine_counts[:fine_steps])
    upper = end(1, values_hi, found_hi, fine_counts[fine_steps:])

    keep = valid_K[face // 6]
    return jnp.where(keep, at(0.5 * (lower + upper)), faces), None

  # the valid boxes' faces in order (an invalid box's step leaves the faces as they are):
  # a loop as long as this object's valid faces, so that two blocks cost 12 steps, not 30
  order = (valid_first(valid_K)[:, None] * 6 + jnp.arange(6)).reshape(-1)
  return jax.lax.fori_loop(0, 6 * jnp.sum(valid_K), lambda i, f: one(f, order[i])[0],
                           faces_Kx6)


def valid_first(valid):
  """(..., K) slot indices with the valid boxes first, each group in slot order."""
  return jnp.argsort(~valid, axis=-1, stable=True)


def map_by_box_count(fn, prims: Primitives, *per_object, chunk: int, slots: bool = False):
  """`jax.lax.map(fn, (prims, *per_object), batch_size=chunk)` with the objects ordered by
  their number of valid boxes (B, K): each chunk of `sweep_faces` then loops as long as its
  own objects need (a vmapped loop runs as long as its longest member); results come back
  in the given order.

  With `slots`, `fn` also sees only as many box slots as its chunk needs: each chunk runs
  one of K - 1 branches (`jax.lax.switch` on the chunk's most valid boxes, at least 2), whose
  boxes are the objects' valid ones first, in their order, cut to that many slots; `fn` must
  return Primitives of the slots it was given, which go back to their places (the slots cut
  off come back as they were). Work that tests every ray against every slot (the image
  fit's labels) then costs a two-block chunk 2/K of a full one; it compiles `fn` K - 1 times.
  """
  order = jnp.argsort(jnp.sum(prims.valid, -1), stable=True)
  take = lambda x: jax.tree.map(lambda a: a[order], x)
  args = take((prims,) + tuple(per_object))
  if slots:
    out = _map_chunks_by_slots(fn, args, chunk)
  else:
    out = jax.lax.map(lambda a: fn(*a), args, batch_size=chunk)
  return jax.tree.map(lambda a: a[jnp.argsort(order)], out)


def _map_chunks_by_slots(fn, args, chunk: int):
  """`map_by_box_count(slots=True)`'s loop over chunks of already ordered objects."""
  b, k_all = args[0].valid.shape
  chunk = min(chunk, b)
  n = -(-b // chunk)
  pad = n * chunk - b  # the last chunk filled with the first object (fewest boxes), dropped
  grow = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], pad, 0)]) if pad else a
  chunks = jax.tree.map(lambda a: grow(a).reshape((n, chunk) + a.shape[1:]), args)
  sizes = tuple(range(min(2, k_all), k_all + 1))
  rows = jnp.arange(chunk)[:, None]

  def branch(k):
    def run(c):
      p = c[0]
      slot = valid_first(p.valid)[:, :k]
      got = jax.vmap(fn)(jax.tree.map(lambda a: a[rows, slot], p), *c[1:])
      return jax.tree.map(lambda full, part: full.at[rows, slot].set(part), p, got)
    return run

  def one_chunk(c):
    most = jnp.max(jnp.sum(c[0].valid, -1))
    index = jnp.searchsorted(jnp.asarray(sizes), most)  # the first size that holds them
    return jax.lax.switch(jnp.clip(index, 0, len(sizes) - 1), [branch(k) for k in sizes], c)

  out = jax.lax.map(one_chunk, chunks)
  return jax.tree.map(lambda a: a.reshape((n * chunk,) + a.shape[2:])[:b], out)


def check_depth(depth, camera: dict, batch: tuple[int, ...]) -> None:
  """ValueError naming the problem with a depth batch (B..., H, W) for `batch` objects."""
  shape = tuple(np.shape(depth))
  if camera is None:
    raise ValueError("depth was given without its camera (storage.Dataset.camera)")
  cam = check_camera(camera, shape if len(shape) >= 2 else None)
  if shape != tuple(batch) + (cam["height"], cam["width"]):
    raise ValueError(f"depth: expected shape {tuple(batch) + (cam['height'], cam['width'])} "
                     f"for the voxels' batch {tuple(batch)}, got {shape}")
  if not isinstance(depth, jax.core.Tracer):
    d = np.asarray(depth)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
      raise ValueError("depth: values must be finite and > 0 (metres)")
