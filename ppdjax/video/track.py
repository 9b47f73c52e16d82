"""`track_poses`: a video of a stickered object to its trajectory in the simulator's
convention (paper Sec. 5.3).

Per frame: detect the red stickers (`stickers.detect_stickers`); predict where each
sticker should be from the poses of the frames before (constant velocity); assign
detections to stickers by minimum total distance within a gate (`pose.match`), so a
sticker that vanishes simply goes unmatched and is found again when it reappears; with
>= 4 matches solve PnP from the prediction and refine it by Levenberg-Marquardt
(`pose.solve_pnp`), then match twice more at the solved pose within a tight gate and
solve again; a frame whose pose fewer than 4 stickers confirm counts as unseen. Frames with
fewer than 4 stickers are interpolated from their neighbours, unless such a run lasts
longer than `max_gap_s` (then `TrackingError` names the frames). The poses are optionally
smoothed and resampled to the simulator's dt.
"""

from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import TIMESTEP
from ppdjax.video import pose as posemod
from ppdjax.video.stickers import detect_stickers

MIN_STICKERS = 4


class TrackingError(ValueError):
  """The stickers could not be followed (too few seen for too long)."""


def _check(frames, intrinsics, camera_from_world, stickers, initial_pose, fps):
  if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8:
    raise ValueError(f"frames must be a uint8 numpy array, got "
                     f"{getattr(frames, 'dtype', type(frames).__name__)}")
  if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 2:
    raise ValueError(f"frames must be (T, H, W, 3) RGB with T >= 2, got {frames.shape}")
  k = np.asarray(intrinsics, np.float64)
  if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
    raise ValueError(f"intrinsics must be a finite (3, 3) matrix with positive focal "
                     f"lengths, got shape {k.shape}")
  c = np.asarray(camera_from_world, np.float64)
  if c.shape != (4, 4) or not np.all(np.isfinite(c)):
    raise ValueError(f"camera_from_world must be a finite (4, 4) matrix, got {c.shape}")
  if not np.allclose(c[:3, :3] @ c[:3, :3].T, np.eye(3), atol=1e-4):
    raise ValueError("camera_from_world's rotation block is not orthonormal")
  s = np.asarray(stickers, np.float64)
  if s.ndim != 2 or s.shape[1] != 3 or len(s) < MIN_STICKERS or not np.all(np.isfinite(s)):
    raise ValueError(f"stickers must be finite (N, 3) object-frame points with N >= "
                     f"{MIN_STICKERS}, got shape {s.shape}")
  p = np.asarray(initial_pose, np.float64)
  if p.shape != (7,) or not np.all(np.isfinite(p)) or abs(np.linalg.norm(p[3:]) - 1) > 1e-3:
    raise ValueError(f"initial_pose must be a finite (7,) pose with a unit quaternion "
                     f"(w, x, y, z), got {p}")
  if not (np.isfinite(fps) and fps > 0):
    raise ValueError(f"fps must be finite and positive, got {fps}")
  return k, c, s, p


def _check_options(n_frames, fps, push_time, dt, steps, gate_px, max_gap_s, smoothing,
                   exposure):
  """ValueError naming the first option out of its range (`track_poses`'s Args)."""
  finite = lambda x: isinstance(x, (int, float, np.number)) and np.isfinite(x)
  if not (finite(exposure) and 0 <= exposure <= 1):
    raise ValueError(f"exposure must be a fraction of the frame period in [0, 1], got "
                     f"{exposure!r}")
  last = (n_frames - 1 - exposure / 2) / fps  # what the last frame shows, dated
  if not (finite(push_time) and 0 <= push_time < last):
    raise ValueError(f"push_time must be in [0, {last:.4g}) s, inside the video ({n_frames} "
                     f"frames at {fps:g} fps), got {push_time!r}")
  if not (finite(dt) and dt > 0):
    raise ValueError(f"dt must be finite and > 0 s, got {dt!r}")
  if steps is not None and (isinstance(steps, bool) or not isinstance(steps, (int, np.integer))
                            or steps < 1):
    raise ValueError(f"steps must be None or an int >= 1, got {steps!r}")
  if gate_px is not None and not (finite(gate_px) and gate_px > 0):
    raise ValueError(f"gate_px must be None or finite and > 0 pixels, got {gate_px!r}")
  for name, value in (("max_gap_s", max_gap_s), ("smoothing", smoothing)):
    if not (finite(value) and value >= 0):
      raise ValueError(f"{name} must be finite and >= 0, got {value!r}")


def track_poses(frames: np.ndarray, intrinsics: np.ndarray, camera_from_world: np.ndarray,
                stickers: np.ndarray, initial_pose: np.ndarray, *, fps: float = 60.0,
                push_time: float = 0.0, dt: float = TIMESTEP, steps: int | None = None,
                gate_px: float | None = None, max_gap_s: float = 0.1,
                smoothing: float = 0.0, exposure: float = 0.0,
                detector: dict | None = None, progress: bool = False) -> np.ndarray:
  """(steps, 7) float32 trajectory of the object frame in world coordinates, one pose
  per simulator step after the push: step k at push_time + (k + 1) dt.

  Args:
    frames: (T, H, W, 3) uint8 RGB video, frame i at time i / fps.
    intrinsics: (3, 3) camera matrix; camera_from_world: (4, 4), OpenCV camera axes.
    stickers: (N, 3) sticker centres in the object frame, N >= 4.
    initial_pose: (7,) the object's pose at rest (world frame), in frame 0.
    fps: the video's frame rate, finite and > 0.
    push_time: when the push starts, seconds on the video's clock, within the video.
    dt: the simulator's step (s), > 0.
    steps: how many simulator steps to return (default: as many as the video covers).
    gate_px: farthest a detection may lie from its sticker's predicted position
      (default 5 % of the frame's larger side).
    max_gap_s: longest run of frames with fewer than 4 stickers that is interpolated.
    smoothing: Gaussian smoothing of the poses over time, in frames (0: none).
    exposure: the shutter's open time as a fraction of the frame period (shutter time x
      fps), the exposure ending at each frame's time i / fps: a blurred frame shows the
      object where it was in the middle of its exposure, exposure / (2 fps) earlier (0:
      an instantaneous shutter). Unaccounted, it delays the whole trajectory.
    detector: keyword arguments of `detect_stickers` (min_area, max_area, min_saturation).
  """
  k, cam_world, pts, p0 = _check(frames, intrinsics, camera_from_world, stickers,
                                 initial_pose, fps)
  n_frames, height, width = frames.shape[:3]
  _check_options(n_frames, fps, push_time, dt, steps, gate_px, max_gap_s, smoothing,
                 exposure)
  gate = gate_px if gate_px is not None else 0.05 * max(height, width)
  world_cam = np.linalg.inv(cam_world)
  cam_obj = [None] * n_frames
  track = [(0, cam_world @ posemod.pose_to_matrix(p0))]  # the last two tracked frames
  for t in tqdm(range(n_frames), desc="tracking", unit="frame", disable=not progress):
    guess = posemod.extrapolate(track, t)
    det = detect_stickers(frames[t], **(detector or {}))
    solved = None
    # a coarse match at the prediction, then matches at the solved pose within a tight
    # gate: a frame is kept only if >= 4 stickers agree with its pose to a few pixels
    for g in (gate, max(3.0, gate / 8), max(3.0, gate / 8)):
      first = solved is None
      start = guess if first else solved
      uv, front = posemod.project(pts, start, k)
      inside = front & (uv[:, 0] > -g) & (uv[:, 0] < width + g) & (uv[:, 1] > -g) & (
          uv[:, 1] < height + g)
      which = posemod.match(det, uv, inside, g)
      ok = which >= 0
      if ok.sum() < MIN_STICKERS:
        solved = None
        break
      solved = posemod.solve_pnp(pts[ok], det[which[ok]], k, start,
                                 ransac_px=max(3.0, gate / 8) if first else None)
      if solved is None:
        break
    if solved is not None:
      cam_obj[t] = solved
      track = [(t, solved)] if t == 0 else [track[-1], (t, solved)]
  seen = np.array([m is not None for m in cam_obj])
  _check_gaps(seen, fps, max_gap_s)
  # when each frame shows the object: the middle of its exposure
  times = np.arange(n_frames) / fps - exposure / (2 * fps)
  tracked = np.stack([posemod.matrix_to_pose(world_cam @ m) for m in cam_obj if m is not None])
  if not seen[0]:  # before the first sighting the object is still at rest
    tracked, seen_times = np.concatenate([p0[None], tracked]), np.concatenate(
        [[times[0]], times[seen]])
  else:
    seen_times = times[seen]
  poses = posemod.resample(seen_times, tracked, np.clip(times, seen_times[0], seen_times[-1]))
  poses = posemod.smooth(poses, smoothing)
  available = int(np.floor((times[-1] - push_time) / dt + 1e-9))
  steps = available if steps is None else steps
  if steps < 1 or steps > available:
    raise ValueError(f"the video covers {available} simulator steps of {dt:.5f} s after "
                     f"the push at {push_time} s, {steps} were asked for")
  return posemod.resample(times, poses, push_time + dt * np.arange(1, steps + 1)
                          ).astype(np.float32)


def _check_gaps(seen: np.ndarray, fps: float, max_gap_s: float) -> None:
  """Raises TrackingError naming the first run of unseen frames longer than max_gap_s."""
  if not seen.any():
    raise TrackingError(f"fewer than {MIN_STICKERS} stickers were matched in every frame")
  limit = max(1, int(round(max_gap_s * fps)))
  t, n = 0, len(seen)
  while t < n:
    if seen[t]:
      t += 1
      continue
    end = t
    while end < n and not seen[end]:
      end += 1
    if end - t > limit:
      raise TrackingError(
          f"fewer than {MIN_STICKERS} stickers were matched in frames {t}-{end - 1} "
          f"({(end - t) / fps:.3f} s, more than max_gap_s={max_gap_s})")
    t = end
