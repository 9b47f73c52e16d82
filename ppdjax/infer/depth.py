"""Depth images of boxes by ray casting in JAX (nearest hit per pixel), and their residuals
against an observed depth image, differentiable in the boxes' faces.

The camera is `dataset.camera`'s pinhole model (OpenCV axes); a depth image holds z along
the optical axis, as MuJoCo renders it. Boxes are in the object frame and stand on the
ground as the dataset's objects do (`sim.scene.rest_position`). Products run at full
float32 precision (`jax.default_matmul_precision("highest")`): GPUs multiply float32 in
TF32 by default, whose 1e-3 relative error is millimetres at the camera's 2.6 m.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.dataset.camera import check_camera
from ppdjax.primitives import Primitives, quat_to_mat
from ppdjax.sim.scene import rest_position

FAR = 100.0  # m: the depth of a ray that meets nothing
OBJECT_MARGIN = 3e-3  # m: observed pixels this much nearer than the floor are the object's


def rays(camera: dict) -> tuple[jax.Array, jax.Array]:
  """The camera's centre (3,) and per-pixel ray directions (H, W, 3) in the world, scaled so
  that a point at ray parameter t lies at depth z = t."""
  cam = check_camera(camera)
  with jax.default_matmul_precision("highest"):
    return camera_rays(jnp.asarray(cam["intrinsics"], jnp.float32),
                       jnp.asarray(cam["camera_from_world"], jnp.float32),
                       cam["height"], cam["width"])


def camera_rays(intrinsics, camera_from_world, height: int, width: int):
  """`rays` from the camera's arrays (traceable; the image size is static)."""
  k, rot, trans = intrinsics, camera_from_world[:3, :3], camera_from_world[:3, 3]
  uu, vv = jnp.meshgrid(jnp.arange(width) + 0.5, jnp.arange(height) + 0.5)  # columns, rows
  pix = jnp.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], jnp.ones_like(uu)], -1)
  return -rot.T @ trans, pix @ rot


def slabs(origin, dirs_Nx3, prims: Primitives):
  """Ray-box entry and exit parameters (N, K) of rays against boxes in the world."""
  rot = quat_to_mat(prims.quat)  # (K, 3, 3) box-to-world
  o = jnp.einsum("kji,kj->ki", rot, origin[None] - prims.pos)  # (K, 3) in the box frames
  d = jnp.einsum("kji,nj->nki", rot, dirs_Nx3)  # (N, K, 3)
  d = jnp.where(jnp.abs(d) < 1e-9, 1e-9, d)
  t1 = (-prims.half_size - o) / d
  t2 = (prims.half_size - o) / d
  return jnp.minimum(t1, t2).max(-1), jnp.maximum(t1, t2).min(-1)


def floor_depth(origin, dirs_Nx3):
  """Depth (N,) where each ray meets the ground plane z = 0 (FAR if it does not)."""
  dz = dirs_Nx3[:, 2]
  t = jnp.where(dz < -1e-9, -origin[2] / jnp.minimum(dz, -1e-9), FAR)
  return jnp.minimum(t, FAR)


def nearest_hits(origin, dirs_Nx3, world: Primitives):
  """Per ray: whether it meets a valid box (N,), the nearest such box (N,), and the
  entry and exit parameters against every box (N, K)."""
  t_in, t_out = slabs(origin, dirs_Nx3, world)
  hit = (t_in <= t_out) & (t_out > 0) & world.valid[None]
  return hit.any(-1), jnp.argmin(jnp.where(hit, t_in, FAR), -1), t_in, t_out


def to_world(prims: Primitives) -> Primitives:
  """Boxes of one object (object frame) at rest on the ground, in the world."""
  return prims.replace(pos=prims.pos + rest_position(prims))


def render_depth(prims: Primitives, camera: dict) -> jax.Array:
  """(H, W) depth of one object (K boxes, object frame) at rest, with the ground plane."""
  origin, dirs = rays(camera)
  h, w = dirs.shape[:2]
  dirs = dirs.reshape(-1, 3)
  with jax.default_matmul_precision("highest"):
    any_hit, box, t_in, _ = nearest_hits(origin, dirs, to_world(prims))
  t_box = jnp.where(any_hit, jnp.maximum(jnp.take_along_axis(t_in, box[:, None], -1)[:, 0],
                                         0.0), FAR)
  return jnp.minimum(t_box, floor_depth(origin, dirs)).reshape(h, w)


def object_mask(depth_HW, camera: dict) -> jax.Array:
  """(H·W,) bool: pixels whose observed depth is nearer than the bare floor's and no
  farther than the space an object can occupy (the unit cube on the ground: the sky's
  far plane is not the object)."""
  cam = check_camera(camera)
  with jax.default_matmul_precision("highest"):
    return mask_from_rays(depth_HW, *rays(cam), jnp.asarray(cam["camera_from_world"]))


def mask_from_rays(depth_HW, origin, dirs_HWx3, camera_from_world) -> jax.Array:
  """`object_mask` from the rays and the camera's pose (traceable)."""
  floor = floor_depth(origin, dirs_HWx3.reshape(-1, 3))
  corners = jnp.asarray(np.stack(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [0.0, 1.0]), -1)
                        .reshape(-1, 3), jnp.float32)
  farthest = (corners @ camera_from_world[:3, :3].T + camera_from_world[:3, 3])[:, 2].max()
  d = depth_HW.reshape(-1)
  return (d < floor - OBJECT_MARGIN) & (d <= farthest)


def residuals(prims: Primitives, depth_N, mask_N, origin, dirs_Nx3) -> jax.Array:
  """(N,) metres, zero where the boxes explain the observed depth `depth_N`.

  On pixels of the object (`mask_N`) that a box covers: rendered minus observed depth. On
  pixels of the object that no box covers: how far the nearest box misses the ray
  (entry minus exit parameter), which pulls a silhouette edge out to it. On background
  pixels that a box covers: the length of the ray inside the nearest box, which pushes
  the edge back. Faces the camera cannot see get no gradient from here.
  """
  world = to_world(prims)
  any_hit, nearest, t_in, t_out = nearest_hits(origin, dirs_Nx3, world)
  valid = world.valid[None]
  t_near = jnp.take_along_axis(t_in, nearest[:, None], -1)[:, 0]
  inside = jnp.take_along_axis(t_out - t_in, nearest[:, None], -1)[:, 0]
  gap = jnp.where(valid, t_in - t_out, FAR).min(-1)
  return jnp.where(mask_N, jnp.where(any_hit, t_near - depth_N, gap),
                   jnp.where(any_hit, inside, 0.0))
