"""Reading what `python -m ppdjax.track` takes: a video file (OpenCV's FFmpeg reader), a
camera JSON and a stickers JSON; each problem raises a ValueError naming the file.

  camera.json:   {"intrinsics": 3x3, "camera_from_world": 4x4}  (OpenCV camera axes)
  stickers.json: {"stickers": Nx3 (object frame, metres), "initial_pose": [px, py, pz,
                  qw, qx, qy, qz] (the pose at rest, world frame)}

and what it writes, which `python -m ppdjax.decompose --trajectory` reads:

  trajectory.npz: trajectory (T, 7) float32 world poses after each step, dt (s),
                  initial_pose (7,)
"""

from __future__ import annotations

import json
import os

import cv2
import numpy as np

from ppdjax.conventions import TIMESTEP


def read_video(path: str) -> tuple[np.ndarray, float]:
  """(T, H, W, 3) uint8 RGB frames and the file's frame rate."""
  if not os.path.isfile(path):
    raise ValueError(f"{path}: no such video file")
  capture = cv2.VideoCapture(path)
  frames = []
  try:
    fps = float(capture.get(cv2.CAP_PROP_FPS))
    while True:
      ok, frame = capture.read()
      if not ok:
        break
      frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
  finally:
    capture.release()
  if len(frames) < 2:
    raise ValueError(f"{path}: not a readable video (got {len(frames)} frames)")
  return np.stack(frames), fps


def _read_json(path: str, keys: tuple[str, ...]) -> dict:
  try:
    with open(path) as f:
      data = json.load(f)
  except FileNotFoundError:
    raise ValueError(f"{path}: no such file") from None
  except json.JSONDecodeError as e:
    raise ValueError(f"{path}: not valid JSON ({e})") from None
  missing = [k for k in keys if not isinstance(data, dict) or k not in data]
  if missing:
    raise ValueError(f"{path}: missing {', '.join(missing)}")
  try:
    return {k: np.asarray(data[k], np.float64) for k in keys}
  except (TypeError, ValueError):
    raise ValueError(f"{path}: {', '.join(keys)} must be arrays of numbers") from None


def read_camera(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(3, 3) intrinsics and (4, 4) camera_from_world (shapes are checked by track_poses)."""
  d = _read_json(path, ("intrinsics", "camera_from_world"))
  return d["intrinsics"], d["camera_from_world"]


def read_stickers(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(N, 3) sticker centres and the (7,) pose at rest."""
  d = _read_json(path, ("stickers", "initial_pose"))
  return d["stickers"], d["initial_pose"]


def read_trajectory(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(T, 7) tracked world poses and the (7,) pose at rest from a `ppdjax.track` .npz."""
  if not os.path.isfile(path):
    raise ValueError(f"{path}: no such trajectory file")
  try:
    with np.load(path) as f:
      data = {k: np.asarray(f[k], np.float64) for k in ("trajectory", "dt", "initial_pose")
              if k in f}
  except (OSError, ValueError) as e:
    raise ValueError(f"{path}: not a readable .npz ({e})") from None
  missing = [k for k in ("trajectory", "dt", "initial_pose") if k not in data]
  if missing:
    raise ValueError(f"{path}: missing {', '.join(missing)} (written by python -m ppdjax.track)")
  traj, pose0 = data["trajectory"], data["initial_pose"]
  if traj.ndim != 2 or traj.shape[1] != 7 or pose0.shape != (7,):
    raise ValueError(f"{path}: expected trajectory (T, 7) and initial_pose (7,), got "
                     f"{traj.shape} and {pose0.shape}")
  if not (np.all(np.isfinite(traj)) and np.all(np.isfinite(pose0))):
    raise ValueError(f"{path}: trajectory or initial_pose contains NaN or inf")
  if abs(float(data["dt"]) - TIMESTEP) > 1e-9:
    raise ValueError(f"{path}: dt is {float(data['dt'])} s; the simulator's is {TIMESTEP} s")
  return traj, pose0


def tracked_observation(path: str, config, rest_height: float) -> np.ndarray:
  """(1, steps, 7) the tracked trajectory of `path` as a model with `config` reads it: in
  the simulator's convention (`pose.relative_to_rest`, the object at rest with its
  object-frame origin `rest_height` above the ground), cut to config.data.steps."""
  from ppdjax.video import pose  # pylint: disable=import-outside-toplevel
  traj, initial_pose = read_trajectory(path)
  steps, pushes = int(config.data.steps), int(config.model.num_pushes)
  if pushes != 1:
    raise ValueError(f"the model reads {pushes} pushes per object; {path} holds one tracked "
                     "trajectory: use a model trained on one strike (assets/video_model)")
  if len(traj) < steps:
    raise ValueError(f"{path}: {len(traj)} steps tracked, the model reads {steps}: film "
                     "longer or track with --steps")
  return pose.relative_to_rest(traj[:steps], initial_pose, np.array([0.0, 0.0, rest_height])
                               )[None]
