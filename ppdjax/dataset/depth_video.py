"""Raw depth videos of pushed objects: the physics observation of the paper's RGB-D row
(Table 2: "replacing the 3D trajectory with a raw depth video"), made on the device.

A video is a function of the object's boxes and its trajectories, so it is rendered where
it is read (the training step, the evaluation's batch) instead of being stored per sample:
at the RGB-D preset's 16 frames of 64 x 64 per push it would be 1 MiB a sample. Each frame
is the exact ray cast of `dataset.depth` (the datasets' depth camera, at the video's size)
of the boxes placed by the trajectory's pose at that frame's step, over the ground.

Frames are spread evenly over the recorded steps, the first just after the push (step 0)
and the last at the trajectory's end (`frame_steps`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import DEPTH_VIDEO, STEPS
from ppdjax.dataset.camera import camera_dict
from ppdjax.dataset.depth import camera_rays, depth_of_world
from ppdjax.primitives import Primitives, quat_mul, quat_to_mat


def frame_steps(frames: int, steps: int = STEPS) -> np.ndarray:
  """(frames,) the recorded steps the frames show: evenly spaced from 0 to steps - 1."""
  if not 2 <= frames <= steps:
    raise ValueError(f"config.model.video_frames must be in 2..{steps} (the recorded steps), "
                     f"got {frames}")
  return np.round(np.linspace(0, steps - 1, frames)).astype(np.int32)


def video_camera(size: int) -> dict:
  """The datasets' camera at size x size pixels (what a depth video is seen by)."""
  return camera_dict(size, size)


def posed(prims: Primitives, pose_7: jax.Array) -> Primitives:
  """Boxes of the object frame placed in the world by a trajectory's pose
  (px, py, pz, qw, qx, qy, qz) of the object frame."""
  rot = quat_to_mat(pose_7[3:])
  return prims.replace(pos=pose_7[:3] + prims.pos @ rot.T,
                       quat=quat_mul(jnp.broadcast_to(pose_7[3:], prims.quat.shape), prims.quat))


def object_video(prims: Primitives, traj_PxTx7: jax.Array, frames: int, origin,
                 dirs_SxSx3) -> jax.Array:
  """(P, F, S, S) depth video of one object (K boxes) under each of its P pushes."""
  poses = traj_PxTx7[:, frame_steps(frames, traj_PxTx7.shape[1])]  # (P, F, 7)
  one = lambda pose: depth_of_world(posed(prims, pose), origin, dirs_SxSx3)
  return jax.vmap(jax.vmap(one))(poses)


@functools.partial(jax.jit, static_argnames=("frames", "size"))
def depth_videos(prims: Primitives, traj_BxPxTx7: jax.Array, frames: int,
                 size: int) -> jax.Array:
  """(B, P, F, S, S) float32 depth videos of B objects (boxes (B, K) in the object frame;
  trajectories (B, P, T, 7))."""
  cam = video_camera(size)
  with jax.default_matmul_precision("highest"):  # millimetres at 2.6 m (`dataset.depth`)
    origin, dirs = camera_rays(jnp.asarray(cam["intrinsics"], jnp.float32),
                               jnp.asarray(cam["camera_from_world"], jnp.float32), size, size)
    traj = traj_BxPxTx7.astype(jnp.float32)
    # 32 objects at a time: a batch of 256 at once would hold ~4 GB per ray-box array
    return jax.lax.map(lambda pt: object_video(*pt, frames, origin, dirs), (prims, traj),
                       batch_size=32)


def with_depth_video(batch: dict, video: tuple[int, int] | None) -> dict:
  """`batch` with the depth videos a model reads (`video`: its (frames, size), None if it
  reads none) rendered from the batch's true boxes ("primitives") and trajectories,
  unless the batch has them or has no trajectories (the geometry stream); traceable."""
  if video is None or DEPTH_VIDEO in batch or "trajectories" not in batch:
    return batch
  return {**batch, DEPTH_VIDEO: depth_videos(batch["primitives"], batch["trajectories"],
                                             *video)}
