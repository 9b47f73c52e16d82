"""Residuals of boxes against an observed depth image (differentiable in the boxes' faces),
and which pixels show the object; the ray cast itself is `dataset.depth`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.dataset.camera import check_camera
from ppdjax.dataset.depth import FAR, floor_depth, nearest_hits, rays, to_world
from ppdjax.primitives import Primitives

OBJECT_MARGIN = 3e-3  # m: observed pixels this much nearer than the floor are the object's


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
