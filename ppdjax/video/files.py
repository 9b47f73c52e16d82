"""Reading what `python -m ppdjax.track` takes: a video file (OpenCV's FFmpeg reader), a
camera JSON and a stickers JSON; each problem raises a VideoFileError (a ValueError)
naming the file, a missing file MissingFileError (also a FileNotFoundError).

  camera.json:   {"intrinsics": 3x3, "camera_from_world": 4x4}  (OpenCV camera axes),
                 optionally "distortion": [k1, k2, p1, p2, k3] (OpenCV's lens model;
                 `python -m ppdjax.calibrate` writes all three)
  stickers.json: {"stickers": Nx3 (object frame, in the units of camera_from_world: the
                  normalised object's, docs/video.md), "initial_pose": [px, py, pz,
                  qw, qx, qy, qz] (the pose at rest, world frame)}

and what it writes, which `python -m ppdjax.decompose --trajectory` reads:

  trajectory.npz: trajectory (T, 7) float32 world poses after each step, dt (s),
                  initial_pose (7,)
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from ppdjax.conventions import TIMESTEP
from ppdjax.dataset.readers import read_json, read_npz

QUAT_TOL = 1e-3  # |q| - 1 allowed in a file (track_poses' initial_pose check)


class VideoFileError(ValueError):
  """A video, camera, stickers or trajectory file that cannot be used (names the file)."""


class MissingFileError(VideoFileError, FileNotFoundError):
  """A file that is not there."""


def read_video(path: str) -> tuple[np.ndarray, float]:
  """(T, H, W, 3) uint8 RGB frames (T >= 2) and the file's frame rate (frames/s; 0 or
  less where the container does not say). Any format OpenCV's FFmpeg reader takes."""
  if not os.path.isfile(path):
    raise (VideoFileError(f"{path}: a directory, not a video file") if os.path.isdir(path)
           else MissingFileError(f"{path}: no such video file"))
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
    raise VideoFileError(f"{path}: not a readable video (got {len(frames)} frames)")
  return np.stack(frames), fps


def read_image(path: str) -> np.ndarray:
  """(H, W, 3) uint8 RGB from an image file (any format OpenCV reads)."""
  if not os.path.isfile(path):
    raise (VideoFileError(f"{path}: a directory, not an image file") if os.path.isdir(path)
           else MissingFileError(f"{path}: no such image file"))
  image = cv2.imread(path, cv2.IMREAD_COLOR)
  if image is None:
    raise VideoFileError(f"{path}: not a readable image")
  return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _read_json(path: str, shapes: dict[str, tuple]) -> dict:
  """The arrays named by `shapes` ({key: shape, -1 any length}) from a JSON object."""
  data = read_json(path, error=VideoFileError, missing=MissingFileError)
  missing = [k for k in shapes if k not in data]
  if missing:
    raise VideoFileError(f"{path}: missing {', '.join(missing)}")
  out = {}
  for k, shape in shapes.items():
    try:
      out[k] = np.asarray(data[k], np.float64)
    except (TypeError, ValueError):
      raise VideoFileError(f"{path}: {k} must be an array of numbers") from None
    if out[k].ndim != len(shape) or any(n not in (-1, m) for n, m in zip(shape, out[k].shape)):
      want = "(" + ", ".join("N" if n == -1 else str(n) for n in shape) + ")"
      raise VideoFileError(f"{path}: {k} must be {want}, got shape {out[k].shape}")
    if not np.all(np.isfinite(out[k])):
      raise VideoFileError(f"{path}: {k} contains NaN or inf")
  return out


def read_camera(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(3, 3) intrinsics (pixels) and (4, 4) camera_from_world (metres, OpenCV axes) from a
  JSON object; shapes and finiteness are checked here, the values by track_poses."""
  d = _read_json(path, {"intrinsics": (3, 3), "camera_from_world": (4, 4)})
  return d["intrinsics"], d["camera_from_world"]


def read_distortion(path: str) -> np.ndarray | None:
  """camera.json's lens distortion ((4,) k1, k2, p1, p2 or (5,) with k3), or None where it
  has none or all zeros (frames then need no undistortion)."""
  data = read_json(path, error=VideoFileError, missing=MissingFileError)
  if "distortion" not in data:
    return None
  try:
    dist = np.asarray(data["distortion"], np.float64)
  except (TypeError, ValueError):
    raise VideoFileError(f"{path}: distortion must be an array of numbers") from None
  if dist.shape not in ((4,), (5,)) or not np.all(np.isfinite(dist)):
    raise VideoFileError(f"{path}: distortion must be 4 or 5 finite numbers (k1, k2, p1, "
                         f"p2[, k3]), got shape {dist.shape}")
  return None if not np.any(dist) else dist


def read_image_size(path: str) -> tuple[int, int] | None:
  """camera.json's (width, height) of the calibration photographs, or None if not given."""
  size = read_json(path, error=VideoFileError, missing=MissingFileError).get("image_size")
  if size is None:
    return None
  if (not isinstance(size, list) or len(size) != 2
      or not all(isinstance(v, int) and v > 0 for v in size)):
    raise VideoFileError(f"{path}: image_size must be [width, height] in pixels, got {size!r}")
  return size[0], size[1]


def undistort(frames: np.ndarray, intrinsics: np.ndarray, distortion: np.ndarray) -> np.ndarray:
  """(T, H, W, 3) frames as a pinhole camera with the same intrinsics sees them."""
  return np.stack([cv2.undistort(f, intrinsics, distortion) for f in frames])


def read_stickers(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(N, 3) sticker centres (object frame, in camera_from_world's units) and the (7,) pose
  at rest (world frame, quaternion w, x, y, z of unit norm) from a JSON object."""
  d = _read_json(path, {"stickers": (-1, 3), "initial_pose": (7,)})
  _check_quaternions(path, "initial_pose", d["initial_pose"][None])
  return d["stickers"], d["initial_pose"]


def _check_quaternions(path: str, name: str, poses_Nx7: np.ndarray) -> None:
  """Unit quaternions (w, x, y, z) in columns 3:7, else VideoFileError naming the first
  bad row: a zero quaternion is no rotation at all and fails later inside scipy."""
  norm = np.linalg.norm(poses_Nx7[:, 3:7], axis=-1)
  bad = np.flatnonzero(np.abs(norm - 1) > QUAT_TOL)
  if bad.size:
    where = f"{name} row {bad[0]}" if len(poses_Nx7) > 1 else name
    raise VideoFileError(f"{path}: {where} has a quaternion of norm {norm[bad[0]]:.4g} "
                         f"({bad.size} such); poses hold unit quaternions (w, x, y, z)")


def read_trajectory(path: str) -> tuple[np.ndarray, np.ndarray]:
  """(T, 7) tracked world poses (px, py, pz in metres, then a unit quaternion w, x, y, z)
  at the simulator's dt, and the (7,) pose at rest, from a `ppdjax.track` .npz (arrays
  "trajectory", "dt" in seconds, "initial_pose")."""
  raw = read_npz(path, "trajectory", error=VideoFileError, missing=MissingFileError)
  missing = [k for k in ("trajectory", "dt", "initial_pose") if k not in raw]
  if missing:
    raise VideoFileError(f"{path}: missing {', '.join(missing)} (written by python -m "
                         "ppdjax.track)")
  try:
    data = {k: np.asarray(raw[k], np.float64) for k in ("trajectory", "dt", "initial_pose")}
  except (TypeError, ValueError) as e:
    raise VideoFileError(f"{path}: trajectory, dt and initial_pose must be numbers") from e
  traj, pose0 = data["trajectory"], data["initial_pose"]
  if traj.ndim != 2 or traj.shape[1] != 7 or len(traj) < 1 or pose0.shape != (7,):
    raise VideoFileError(f"{path}: expected trajectory (T, 7) with T >= 1 and initial_pose "
                         f"(7,), got {traj.shape} and {pose0.shape}")
  if not (np.all(np.isfinite(traj)) and np.all(np.isfinite(pose0))):
    raise VideoFileError(f"{path}: trajectory or initial_pose contains NaN or inf")
  dt = data["dt"].ravel()
  if dt.size != 1 or abs(dt[0] - TIMESTEP) > 1e-9:
    shown = f"{dt[0]:g} s" if dt.size == 1 else f"an array of shape {data['dt'].shape}"
    raise VideoFileError(f"{path}: dt is {shown}; the simulator's is {TIMESTEP} s")
  _check_quaternions(path, "trajectory", traj)
  _check_quaternions(path, "initial_pose", pose0[None])
  return traj, pose0


def tracked_observation(path: str, config, rest_height: float) -> np.ndarray:
  """(1, steps, 7) the tracked trajectory of `path` as a model with `config` reads it: in
  the simulator's convention (`pose.relative_to_rest`, the object at rest with its
  object-frame origin `rest_height` above the ground), cut to config.data.steps."""
  from ppdjax.video import pose  # pylint: disable=import-outside-toplevel
  traj, initial_pose = read_trajectory(path)
  steps, pushes = int(config.data.steps), int(config.model.num_pushes)
  if pushes != 1:
    raise VideoFileError(f"the model reads {pushes} pushes per object; {path} holds one "
                         "tracked trajectory: use a model trained on one strike "
                         "(assets/video_model)")
  if len(traj) < steps:
    raise VideoFileError(f"{path}: {len(traj)} steps tracked, the model reads {steps}: film "
                         "longer or track with --steps")
  return pose.relative_to_rest(traj[:steps], initial_pose, np.array([0.0, 0.0, rest_height])
                               )[None]
