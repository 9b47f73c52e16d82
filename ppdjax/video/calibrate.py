"""A camera for `python -m ppdjax.track`, calibrated from photographs of a printed
checkerboard (OpenCV's calibration): the intrinsics and lens distortion from several views
of the board, then `camera_from_world` from one photograph of the board lying flat on the
table where the object will stand.

The world frame is the one the tracker and the simulator share: z up, the table at z = 0,
its origin at the board's first inner corner (OpenCV's corner order), x along the board's
first row of corners, y across the rows, turned so that z points up out of the table.
"""

from __future__ import annotations

import json
import os

import cv2
import numpy as np

MIN_VIEWS = 3  # OpenCV's calibration needs several views of the board at different tilts
_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


class CalibrationError(ValueError):
  """Photographs a camera cannot be calibrated from (names the files and the reason)."""


def board_points(board: tuple[int, int], square: float) -> np.ndarray:
  """(cols * rows, 3) the board's inner corners in its own frame (metres, z = 0), in the
  order OpenCV finds them: `board` = (corners per row, rows)."""
  cols, rows = board
  grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
  return np.concatenate([grid, np.zeros((len(grid), 1))], 1).astype(np.float64)


def find_board(image: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
  """(cols * rows, 2) sub-pixel corners of the board in an RGB or grey uint8 image, or None
  where the whole board is not seen."""
  grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
  found, corners = cv2.findChessboardCorners(
      grey, tuple(board), flags=cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE)
  if not found:
    return None
  return cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), _SUBPIX).reshape(-1, 2)


def _check(board, square):
  if len(board) != 2 or min(board) < 2:
    raise CalibrationError(f"board must be (corners per row, rows), each >= 2: got {board}")
  if not (square > 0 and np.isfinite(square)):
    raise CalibrationError(f"square must be the side of one square in metres, > 0: got "
                           f"{square}")


def calibrate_intrinsics(images: list[np.ndarray], board: tuple[int, int], square: float,
                         names: list[str] | None = None) -> dict:
  """The intrinsics (3, 3), distortion (5,) (k1, k2, p1, p2, k3) and the RMS reprojection
  error (pixels) from photographs of the board at several tilts; the views where the
  board was found are listed. CalibrationError if fewer than MIN_VIEWS show it or the
  images differ in size."""
  _check(board, square)
  if not images:
    raise CalibrationError("no photographs of the board were given")
  names = names or [f"image {i}" for i in range(len(images))]
  if len(names) != len(images):
    raise CalibrationError(f"{len(names)} names for {len(images)} photographs")
  sizes = {im.shape[:2] for im in images}
  if len(sizes) != 1:
    raise CalibrationError(f"the photographs differ in size {sorted(sizes)}: calibrate one "
                           "camera at one resolution")
  found = [(n, c) for n, im in zip(names, images)
           if (c := find_board(im, board)) is not None]
  if len(found) < MIN_VIEWS:
    missed = [n for n in names if n not in dict(found)]
    raise CalibrationError(
        f"the {board[0]}x{board[1]} board was found in {len(found)} of {len(images)} "
        f"photographs, {MIN_VIEWS} are needed (not found: {', '.join(missed[:5])}): "
        "check the board's inner-corner count and that it is whole and sharp")
  h, w = next(iter(sizes))
  obj = [board_points(board, square).astype(np.float32)] * len(found)
  img = [c.astype(np.float32) for _, c in found]
  # k3 stays 0 (OpenCV's advice for ordinary lenses: with a few views it overfits)
  rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), None, None,
                                           flags=cv2.CALIB_FIX_K3)
  return {"intrinsics": k, "distortion": dist.ravel()[:5], "rms_px": float(rms),
          "views": [n for n, _ in found], "image_size": [int(w), int(h)]}


def camera_from_ground(image: np.ndarray, intrinsics: np.ndarray, distortion: np.ndarray,
                       board: tuple[int, int], square: float, name: str = "ground",
                       image_size: tuple[int, int] | None = None) -> np.ndarray:
  """(4, 4) camera_from_world (OpenCV camera axes) from a photograph of the board lying
  flat on the table (the world frame of the module docstring); `image_size` (width,
  height) the calibration's, which the photograph must have."""
  _check(board, square)
  if image_size is not None and tuple(image.shape[1::-1]) != tuple(image_size):
    raise CalibrationError(f"{name} is {image.shape[1]}x{image.shape[0]} pixels, the "
                           f"calibration photographs {image_size[0]}x{image_size[1]}: take "
                           "all of them at the resolution the camera films at")
  corners = find_board(image, board)
  if corners is None:
    raise CalibrationError(f"{name}: the {board[0]}x{board[1]} board is not found")
  world = board_points(board, square)
  m = _solve(world, corners, intrinsics, distortion)
  if np.linalg.inv(m)[2, 3] < 0:  # the camera below the table: the board's z points down
    world[:, 1] *= -1  # mirror y so that z = x cross y points up
    m = _solve(world, corners, intrinsics, distortion)
  return m


def _solve(world, corners, intrinsics, distortion):
  ok, rvec, tvec = cv2.solvePnP(world, corners.astype(np.float64), intrinsics, distortion,
                                flags=cv2.SOLVEPNP_ITERATIVE)
  if not ok:
    raise CalibrationError("the board's pose could not be solved")
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
  return m


def draw_world_axes(image: np.ndarray, intrinsics: np.ndarray, distortion: np.ndarray,
                    camera_from_world: np.ndarray, length: float) -> np.ndarray:
  """A copy of the RGB image with the world frame's origin and axes drawn (x red, y green,
  z blue, `length` metres): where the user measures the object's rest pose from."""
  out = np.ascontiguousarray(image[..., ::-1])  # OpenCV draws on BGR
  rvec = cv2.Rodrigues(camera_from_world[:3, :3])[0]
  cv2.drawFrameAxes(out, intrinsics, distortion, rvec, camera_from_world[:3, 3], length, 3)
  return out[..., ::-1]


def write_camera(path: str, intrinsics: np.ndarray, camera_from_world: np.ndarray,
                 distortion: np.ndarray | None = None, **extra) -> None:
  """camera.json as `python -m ppdjax.track` reads it (`video.files.read_camera`)."""
  data = {"intrinsics": np.asarray(intrinsics).tolist(),
          "camera_from_world": np.asarray(camera_from_world).tolist(), **extra}
  if distortion is not None:
    data["distortion"] = np.asarray(distortion).ravel().tolist()
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  with open(path, "w") as f:
    json.dump(data, f, indent=1)
