"""Depth images of boxes by exact ray casting in JAX (nearest hit per pixel): the dataset's
depth camera, and what the depth fit (`infer.depth_fit`) compares against.

The camera is `dataset.camera`'s pinhole model (OpenCV axes); a depth image holds z along
the optical axis, as MuJoCo renders it, over an unbounded ground plane (FAR where a ray
meets nothing). Boxes are in the object frame and stand on the ground as the dataset's
objects do (`sim.scene.rest_position`). Products run at full float32 precision
(`jax.default_matmul_precision("highest")`): GPUs multiply float32 in TF32 by default,
whose 1e-3 relative error is millimetres at the camera's 2.6 m.

Why a ray cast and not MuJoCo's GL depth: on a CPU (Mesa) the two agree on object pixels to 0.1 mm
(`tests/test_depth.py`), but the depth buffer of an NVIDIA EGL context differed from the
exact depth by a median 4 mm (p99 12-18 mm) on object pixels, so datasets would differ by
the machine that rendered them (`experiments/results/depth_fit.md`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.dataset.camera import check_camera
from ppdjax.primitives import Primitives, quat_to_mat
from ppdjax.sim.scene import rest_position

FAR = 100.0  # m: the depth of a ray that meets nothing


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
  return depth_from_rays(prims, origin, dirs)


def depth_from_rays(prims: Primitives, origin, dirs_HWx3) -> jax.Array:
  """`render_depth` from the camera's rays (traceable)."""
  return depth_of_world(to_world(prims), origin, dirs_HWx3)


def depth_of_world(world: Primitives, origin, dirs_HWx3) -> jax.Array:
  """(H, W) depth of boxes placed in the world (anywhere: a pushed object's too), with
  the ground plane (traceable)."""
  h, w = dirs_HWx3.shape[:2]
  dirs = dirs_HWx3.reshape(-1, 3)
  with jax.default_matmul_precision("highest"):
    any_hit, box, t_in, _ = nearest_hits(origin, dirs, world)
  t_box = jnp.where(any_hit, jnp.maximum(jnp.take_along_axis(t_in, box[:, None], -1)[:, 0],
                                         0.0), FAR)
  return jnp.minimum(t_box, floor_depth(origin, dirs)).reshape(h, w)


def render_depths(prims: Primitives, camera: dict) -> jax.Array:
  """(N, H, W) float32 depth of N objects (`render_depth` batched, one jitted call)."""
  origin, dirs = rays(camera)
  return _render_depths(jax.tree.map(jnp.asarray, prims), origin, dirs)


@jax.jit
def _render_depths(prims, origin, dirs):  # 16 objects at a time: ~0.5 GB at 224² pixels
  return jax.lax.map(lambda p: depth_from_rays(p, origin, dirs), prims, batch_size=16)
