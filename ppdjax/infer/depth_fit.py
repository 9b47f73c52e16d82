"""Boxes fitted to voxels, refined against a depth image: faces the camera sees become
sub-voxel, faces it cannot see stay where the voxels put them.

Each box's six faces (lo and hi along its own axes) move within `bound` of where the voxel
fit put them (half a voxel: the voxelizer fills every voxel a box shares volume with, so a
face lies within half a voxel of the centre of its last filled voxel). Faces that touch in
the voxel fit (a block standing on another: one's top, the other's bottom) stay touching,
so a visible top carries the hidden bottom above it. Projected Levenberg-Marquardt over the
6K faces on `depth.residuals`, with forward-mode Jacobians (one batched call per step).
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


def _boxes(prims: Primitives, faces_Kx6) -> Primitives:
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


def _ties(prims: Primitives):
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


def refine_batch(prims: Primitives, depth_BxHxW, camera: dict, *, iterations: int = 15
                 ) -> Primitives:
  """`refine_with_depth` over a batch (B, K) of objects seen by one camera (jitted once per
  image size and iteration count; CHUNK objects at a time bound the Jacobians' memory)."""
  cam = check_camera(camera)
  return _refine_batch(prims, jnp.asarray(depth_BxHxW, jnp.float32),
                       jnp.asarray(cam["intrinsics"], jnp.float32),
                       jnp.asarray(cam["camera_from_world"], jnp.float32),
                       iterations=iterations)


@functools.partial(jax.jit, static_argnames="iterations")
def _refine_batch(prims, depth_BxHxW, intrinsics, camera_from_world, iterations):
  one = lambda p, d: refine_with_depth(p, d, intrinsics, camera_from_world,
                                       iterations=iterations)
  with jax.default_matmul_precision("highest"):  # GPUs' TF32 default: mm at 2.6 m
    return jax.lax.map(lambda a: one(*a), (prims, depth_BxHxW), batch_size=CHUNK)


def refine_with_depth(prims: Primitives, depth_HW, intrinsics, camera_from_world, *,
                      bound: float = VOXEL / 2, iterations: int = 15,
                      damping: float = 1e-3) -> Primitives:
  """One object's boxes (K, object frame) refined against its depth image (H, W).

  Pixel residuals pass through ROBUST·arctan(r / ROBUST): a pixel where the rendering hits
  another box than the observation (a box's edge still a few millimetres short, so the ray
  goes on to a box behind) gives a large residual whose gradient moves the wrong box; the
  arctan makes such pixels count for little.

  Args:
    prims: the voxel fit (`fit.fit_boxes`); rotations are kept.
    depth_HW: observed depth (metres along the optical axis), as the dataset stores it.
    intrinsics, camera_from_world: the dataset's camera (`storage.Dataset.camera`).
    bound: how far (m) a face may move from the start.
    iterations: Levenberg-Marquardt steps.
    damping: the starting Levenberg-Marquardt damping.
  """
  h, w = depth_HW.shape
  origin, dirs = camera_rays(intrinsics, camera_from_world, h, w)
  obs = jnp.asarray(depth_HW, jnp.float32).reshape(-1)
  mask = depth_lib.mask_from_rays(obs, origin, dirs, camera_from_world)
  dirs = dirs.reshape(-1, 3)
  ties = _ties(prims)
  rot = quat_to_mat(prims.quat)
  centre_axes = jnp.einsum("kji,kj->ki", rot, prims.pos)
  start = jnp.concatenate([-prims.half_size, prims.half_size], -1)  # (K, 6)
  k = start.shape[0]

  def residual(x):
    faces = x.reshape(k, 6)
    boxes = _boxes(prims, faces)
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
  out = _boxes(prims, x.reshape(k, 6))
  keep = prims.valid[:, None]
  return out.replace(half_size=jnp.where(keep, out.half_size, prims.half_size),
                     pos=jnp.where(keep, out.pos, prims.pos))


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
