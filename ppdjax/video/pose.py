"""Poses from matched stickers: projection, minimum-distance matching, PnP refined by
Levenberg-Marquardt, rigid-body smoothing and resampling to the simulator's dt.

Frames: a pose is a 4x4 homogeneous transform; `camera_from_world` uses OpenCV's camera
axes (x right, y down, z forward); trajectories use the project's (T, 7) convention
(px, py, pz, qw, qx, qy, qz), the object frame in world coordinates.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation, Slerp


def pose_to_matrix(pose7: np.ndarray) -> np.ndarray:
  """4x4 world_from_object of a (7,) pose (px, py, pz, qw, qx, qy, qz)."""
  m = np.eye(4)
  m[:3, :3] = Rotation.from_quat(np.asarray(pose7[3:], np.float64), scalar_first=True
                                 ).as_matrix()
  m[:3, 3] = pose7[:3]
  return m


def matrix_to_pose(m: np.ndarray) -> np.ndarray:
  """(7,) pose of a 4x4 world_from_object, quaternion with qw >= 0."""
  q = Rotation.from_matrix(m[:3, :3]).as_quat(scalar_first=True)
  return np.concatenate([m[:3, 3], q if q[0] >= 0 else -q])


def project(points: np.ndarray, camera_from_object: np.ndarray,
            intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(N, 2) pixel positions of (N, 3) object points and (N,) whether each is in front."""
  cam = points @ camera_from_object[:3, :3].T + camera_from_object[:3, 3]
  z = cam[:, 2]
  uv = cam[:, :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[:, None]
  return uv @ intrinsics[:2, :2].T + intrinsics[:2, 2], z > 1e-6


def match(detections: np.ndarray, predicted: np.ndarray, usable: np.ndarray,
          gate: float) -> np.ndarray:
  """(N,) index of the detection assigned to each sticker (-1: none) by minimum total
  distance (Hungarian) between the detections and the stickers' predicted positions;
  pairs farther apart than `gate` pixels are left unmatched."""
  out = np.full(len(predicted), -1)
  idx = np.nonzero(usable)[0]
  if len(detections) == 0 or len(idx) == 0:
    return out
  cost = np.linalg.norm(predicted[idx, None, :] - detections[None, :, :], axis=-1)
  rows, cols = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
  ok = cost[rows, cols] <= gate
  out[idx[rows[ok]]] = cols[ok]
  return out


def extrapolate(track: list[tuple[int, np.ndarray]], frame: int) -> np.ndarray:
  """The 4x4 pose at `frame` at constant velocity from the last two (frame, pose) pairs
  of `track` (position linearly, orientation along the same rotation axis)."""
  (f1, m1) = track[-1]
  if len(track) < 2 or track[-2][0] == f1:
    return m1
  f0, m0 = track[-2]
  s = (frame - f1) / (f1 - f0)
  rel = Rotation.from_matrix(m1[:3, :3] @ m0[:3, :3].T).as_rotvec()
  out = np.eye(4)
  out[:3, :3] = Rotation.from_rotvec(s * rel).as_matrix() @ m1[:3, :3]
  out[:3, 3] = m1[:3, 3] + s * (m1[:3, 3] - m0[:3, 3])
  return out


def solve_pnp(object_points: np.ndarray, image_points: np.ndarray, intrinsics: np.ndarray,
              guess: np.ndarray, ransac_px: float | None = None) -> np.ndarray | None:
  """4x4 camera_from_object from >= 4 correspondences: OpenCV's iterative PnP from the
  guess (a 4x4 camera_from_object), then Levenberg-Marquardt on the reprojection error.
  With `ransac_px`, the solve is RANSAC's (pairs off by more than that many pixels are
  outliers, e.g. a detection matched to a hidden sticker) and LM refines the inliers;
  None when fewer than 4 remain."""
  obj = np.ascontiguousarray(object_points, np.float64)
  img = np.ascontiguousarray(image_points, np.float64)
  k = np.asarray(intrinsics, np.float64)
  rvec = cv2.Rodrigues(guess[:3, :3])[0]
  tvec = guess[:3, 3].reshape(3, 1).copy()
  if ransac_px is not None:
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj, img, k, None, rvec, tvec, useExtrinsicGuess=True, iterationsCount=200,
        reprojectionError=ransac_px, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inliers is None or len(inliers) < 4:
      return None
    obj, img = obj[inliers.ravel()], img[inliers.ravel()]
  else:
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
      return None
  rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
  m = np.eye(4)
  m[:3, :3] = cv2.Rodrigues(rvec)[0]
  m[:3, 3] = tvec.ravel()
  return m


def smooth(poses: np.ndarray, sigma: float) -> np.ndarray:
  """(T, 7) poses smoothed over time by a Gaussian of `sigma` frames: positions directly,
  quaternions sign-aligned to their neighbours, smoothed and renormalised (0: unchanged)."""
  if sigma <= 0:
    return poses
  q = poses[:, 3:].copy()
  for t in range(1, len(q)):
    if np.dot(q[t], q[t - 1]) < 0:
      q[t] = -q[t]
  p = gaussian_filter1d(poses[:, :3], sigma, axis=0, mode="nearest")
  q = gaussian_filter1d(q, sigma, axis=0, mode="nearest")
  q /= np.linalg.norm(q, axis=-1, keepdims=True)
  q *= np.where(q[:, :1] < 0, -1.0, 1.0)
  return np.concatenate([p, q], -1)


def resample(times: np.ndarray, poses: np.ndarray, new_times: np.ndarray) -> np.ndarray:
  """(len(new_times), 7) poses at `new_times` (within [times[0], times[-1]]): positions
  interpolated linearly, orientations by spherical linear interpolation."""
  new_times = np.clip(new_times, times[0], times[-1])  # float round-off at the ends
  p = np.stack([np.interp(new_times, times, poses[:, i]) for i in range(3)], -1)
  rot = Slerp(times, Rotation.from_quat(poses[:, 3:], scalar_first=True))(new_times)
  q = rot.as_quat(scalar_first=True)
  return np.concatenate([p, q * np.where(q[:, :1] < 0, -1.0, 1.0)], -1)


def relative_to_rest(trajectory: np.ndarray, initial_pose: np.ndarray,
                     rest_position: np.ndarray) -> np.ndarray:
  """(T, 7) a tracked trajectory in the simulator's convention: the motion since rest,
  expressed in the object frame at rest (W0^-1 W(t)), placed at the convention's rest
  pose (rest_position, identity orientation), so that a tower filmed anywhere on the
  table, turned by any angle about z, reads as the simulated one."""
  rest = np.eye(4)
  rest[:3, 3] = rest_position
  w0_inv = np.linalg.inv(pose_to_matrix(np.asarray(initial_pose, np.float64)))
  return np.stack([matrix_to_pose(rest @ w0_inv @ pose_to_matrix(p))
                   for p in np.asarray(trajectory, np.float64)]).astype(np.float32)
