"""The worked example of docs/video.md: one struck tower filmed as the video test towers
are (`observe.py`'s camera, stickers and degradation), written as a user's files:

  clip.mp4       the video (MPEG-4, 640 x 480 at the test towers' frame rate)
  camera.json    intrinsics and camera_from_world (`python -m ppdjax.track --camera`)
  stickers.json  sticker centres in the object frame and the pose at rest (--stickers)
  tower.glb      the blocks, one group each, bottom to top (`decompose --mesh`)
  truth.json     the blocks' materials and densities, and the true trajectory, to compare
"""

from __future__ import annotations

import json
import os

import cv2
import jax
import numpy as np
import trimesh

from ppdjax.conventions import TIMESTEP
from ppdjax.video import pose as posemod
from ppdjax.video import synthetic
from ppdjax.video.calibrate import write_camera


def tower_mesh(prims, names: list[str]) -> trimesh.Scene:
  """The valid blocks as boxes in the object frame, one named geometry each."""
  scene = trimesh.Scene()
  for k, name in enumerate(names):
    box = trimesh.creation.box(extents=2 * np.asarray(prims.half_size[k], np.float64),
                               transform=posemod.pose_to_matrix(np.concatenate(
                                   [prims.pos[k], prims.quat[k]]).astype(np.float64)))
    scene.add_geometry(box, geom_name=name, node_name=name)
  return scene


def write_example(out: str, prims, material_ids, texture_seeds, rest: np.ndarray,
                  trajectory: np.ndarray, *, fps: float, frame: tuple[int, int],
                  noise: float, lighting: float, stickers: str, seed: int,
                  material_names: list[str]) -> dict:
  """Films one object (numpy Primitives fields, K slots; `trajectory` (T, 7) world poses
  after each step from `rest`) and writes the files of the module docstring into `out`;
  returns truth.json's content."""
  os.makedirs(out, exist_ok=True)
  renderer = synthetic.VideoRenderer(*frame, stickers=stickers)
  try:
    points = renderer.set_object(prims, material_ids, texture_seeds)
    frames = synthetic.film(renderer, rest, trajectory, TIMESTEP, fps)
    video = synthetic.degrade(frames, np.random.default_rng(seed), noise=noise,
                              lighting=lighting)
    intrinsics, camera_from_world = renderer.intrinsics, renderer.camera_from_world
  finally:
    renderer.close()
  writer = cv2.VideoWriter(os.path.join(out, "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                           fps, (frame[1], frame[0]))
  for f in video:
    writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
  writer.release()
  write_camera(os.path.join(out, "camera.json"), intrinsics, camera_from_world,
               image_size=[frame[1], frame[0]])
  with open(os.path.join(out, "stickers.json"), "w") as f:
    json.dump({"stickers": points.tolist(), "initial_pose": np.asarray(rest).tolist()}, f,
              indent=1)
  valid = np.flatnonzero(np.asarray(prims.valid))
  blocks = [f"block{i}" for i in range(len(valid))]
  kept = jax.tree.map(lambda a: np.asarray(a)[valid], prims)
  tower_mesh(kept, blocks).export(os.path.join(out, "tower.glb"))
  truth = {"blocks": blocks,
           "materials": [material_names[int(np.asarray(material_ids)[i])] for i in valid],
           "densities": np.asarray(prims.density)[valid].tolist(), "fps": fps,
           "exposure": synthetic.EXPOSURE,  # the shutter it was filmed with (track --exposure)
           "frames": len(video), "true_trajectory": np.asarray(trajectory).tolist(),
           "dt": TIMESTEP}
  with open(os.path.join(out, "truth.json"), "w") as f:
    json.dump(truth, f)
  return truth
