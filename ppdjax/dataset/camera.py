"""The dataset's fixed pinhole camera: where it is, and its intrinsics in OpenCV's convention.

The renderer (`dataset.render`) places a MuJoCo camera at CAMERA_POS looking at
CAMERA_TARGET with a vertical field of view of FOVY degrees. The same camera as a pinhole
model: `intrinsics` (3, 3) K and `camera_from_world` (4, 4) with OpenCV's camera axes (x
right, y down, z forward), so that a world point X projects to pixel (u, v) = K (R X + t)
/ z with u along the image's columns and v down its rows (pixel centres at +0.5), and a
depth image holds z, the distance along the optical axis (MuJoCo's depth rendering).
Generation writes it into the dataset's manifest; `storage.Dataset.camera` reads it.
"""

from __future__ import annotations

import numpy as np

CAMERA_POS = np.array([1.55, -1.9, 1.35])
CAMERA_TARGET = np.array([0.0, 0.0, 0.45])
FOVY = 40.0  # degrees, vertical
# The scene's one directional light (the renderer's), the direction its light travels: the
# objects' shadows fall on the floor behind them (-x, +y), where the camera sees the back
# faces in silhouette.
LIGHT_DIR = np.array([-0.4, 0.2, -1.0])


def camera_axes() -> np.ndarray:
  """(3, 3) rows: the camera's right, up and forward directions in the world."""
  forward = CAMERA_TARGET - CAMERA_POS
  forward /= np.linalg.norm(forward)
  right = np.cross(forward, [0.0, 0.0, 1.0])
  right /= np.linalg.norm(right)
  up = np.cross(right, forward)
  return np.stack([right, up, forward])


def intrinsics(height: int, width: int) -> np.ndarray:
  """(3, 3) K of an image of height x width pixels (square pixels, centred principal point)."""
  f = 0.5 * height / np.tan(np.radians(FOVY) / 2)
  return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def camera_from_world() -> np.ndarray:
  """(4, 4) rigid transform from world to OpenCV camera coordinates."""
  right, up, forward = camera_axes()
  rot = np.stack([right, -up, forward])
  out = np.eye(4)
  out[:3, :3], out[:3, 3] = rot, -rot @ CAMERA_POS
  return out


def camera_dict(height: int, width: int) -> dict:
  """The camera as stored in a dataset's manifest (JSON-ready), with the scene's light."""
  return {"height": int(height), "width": int(width),
          "intrinsics": intrinsics(height, width).tolist(),
          "camera_from_world": camera_from_world().tolist(),
          "light_dir": LIGHT_DIR.tolist()}


def check_camera(camera: dict, depth_shape: tuple[int, ...] | None = None) -> dict:
  """`camera` as float arrays; ValueError naming the problem if a key, shape or value is bad,
  or if it does not match a depth image of `depth_shape` (..., H, W).

  The optional "light_dir" (3,) is the direction the scene's directional light travels
  (the image fit predicts shadows from it); None: unknown. A camera without the key gets
  LIGHT_DIR: every dataset written before the key existed was rendered under that light.
  """
  if not isinstance(camera, dict):
    raise ValueError(f"camera: expected a dict with height, width, intrinsics and "
                     f"camera_from_world, got {type(camera).__name__}")
  missing = {"height", "width", "intrinsics", "camera_from_world"} - set(camera)
  if missing:
    raise ValueError(f"camera: missing {sorted(missing)}")
  k = np.asarray(camera["intrinsics"], np.float64)
  pose = np.asarray(camera["camera_from_world"], np.float64)
  if k.shape != (3, 3) or pose.shape != (4, 4):
    raise ValueError(f"camera: intrinsics must be (3, 3) and camera_from_world (4, 4), got "
                     f"{k.shape} and {pose.shape}")
  if not (np.all(np.isfinite(k)) and np.all(np.isfinite(pose))):
    raise ValueError("camera: intrinsics or camera_from_world hold NaN or inf")
  if k[0, 0] <= 0 or k[1, 1] <= 0:
    raise ValueError(f"camera: focal lengths must be > 0, got {k[0, 0]}, {k[1, 1]}")
  rot = pose[:3, :3]
  if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0:
    raise ValueError("camera: camera_from_world's rotation is not a rotation")
  size = (camera["height"], camera["width"])
  whole = lambda x: (np.ndim(x) == 0 and not isinstance(x, (bool, np.bool_))
                     and np.issubdtype(np.asarray(x).dtype, np.number)
                     and np.isfinite(x) and float(x) == int(x) and int(x) > 0)
  if not all(whole(x) for x in size):
    raise ValueError(f"camera: height and width must be whole numbers of pixels > 0, got "
                     f"{size[0]!r} x {size[1]!r}")
  h, w = int(size[0]), int(size[1])
  if depth_shape is not None and tuple(depth_shape[-2:]) != (h, w):
    raise ValueError(f"camera is for {h}x{w} images but the depth image is "
                     f"{depth_shape[-2]}x{depth_shape[-1]}")
  light = camera.get("light_dir", LIGHT_DIR)
  if light is not None:
    light = np.array(light, np.float64)  # a copy: callers may edit what they get
    if light.shape != (3,) or not np.all(np.isfinite(light)) or light[2] >= 0:
      raise ValueError(f"camera: light_dir must be 3 finite numbers pointing down (z < 0), "
                       f"or None; got {light.tolist()}")
  return {"height": h, "width": w, "intrinsics": k, "camera_from_world": pose,
          "light_dir": light}
