"""`python -m ppdjax.track --video FILE --camera CAMERA.json --stickers STICKERS.json
--out TRAJ.npz`: a video of a stickered object to its trajectory (paper Sec. 5.3).

Reads the video (any format OpenCV's FFmpeg reader takes; frame rate from the file unless
--fps), undoes the lens distortion where CAMERA.json gives one (and checks its
image_size), tracks the stickers (`ppdjax.video.track_poses`) and writes TRAJ.npz with
"trajectory" (T, 7) float32 at the simulator's dt after the push and "dt". The files'
formats are in `ppdjax/video/files.py` and docs/video.md.

Flags: --fps > 0 frames per second (0: the file's), --push_time >= 0 s on the video's
clock, --steps >= 0 (0: all the video covers), --smoothing >= 0 frames, --exposure in [0, 1]
(the shutter time x fps, the exposure ending at each frame's time; 0: instantaneous),
--out a path ending in .npz. A bad flag is a usage error naming it; a missing or unreadable file a
`files.VideoFileError` naming the file.
"""

from __future__ import annotations

import os

import numpy as np
from absl import app, flags

from ppdjax.conventions import TIMESTEP
from ppdjax.video import files, track_poses

_VIDEO = flags.DEFINE_string("video", None, "Video file.", required=True)
_CAMERA = flags.DEFINE_string("camera", None, "Camera JSON (intrinsics, camera_from_world).",
                              required=True)
_STICKERS = flags.DEFINE_string("stickers", None, "Stickers JSON (stickers, initial_pose).",
                                required=True)
_OUT = flags.DEFINE_string("out", "trajectory.npz", "Output .npz.")
_FPS = flags.DEFINE_float("fps", 0.0, "Frame rate (0: the file's).")
_PUSH_TIME = flags.DEFINE_float("push_time", 0.0, "When the push starts (s, video clock).")
_STEPS = flags.DEFINE_integer("steps", 0, "Simulator steps to write (0: all the video covers).")
_SMOOTHING = flags.DEFINE_float("smoothing", 0.0, "Gaussian smoothing over frames (0: none).")
_EXPOSURE = flags.DEFINE_float("exposure", 0.0, "Shutter time x fps, the exposure ending at "
                               "each frame's time (0: instantaneous).")


def check_flags(fps: float, push_time: float, steps: int, smoothing: float, out: str,
                exposure: float = 0.0) -> None:
  """app.UsageError naming the first flag out of its range, before any file is read."""
  if not (fps >= 0 and np.isfinite(fps)):  # 0 is the default: the file's rate
    raise app.UsageError(f"--fps must be positive (frames per second; 0 reads the video "
                         f"file's rate), got {fps:g}")
  for name, value in (("push_time", push_time), ("steps", steps), ("smoothing", smoothing)):
    if not (value >= 0 and np.isfinite(value)):
      raise app.UsageError(f"--{name} must be >= 0, got {value:g}")
  if not (0 <= exposure <= 1):  # NaN fails too
    raise app.UsageError(f"--exposure must be in [0, 1] (the shutter time x fps), got "
                         f"{exposure:g}")
  if not out.endswith(".npz"):  # np.savez would append ".npz" to any other name
    raise app.UsageError(f"--out must name an .npz file, got {out!r}")


def main(argv):
  del argv
  check_flags(_FPS.value, _PUSH_TIME.value, _STEPS.value, _SMOOTHING.value, _OUT.value,
              _EXPOSURE.value)
  frames, file_fps = files.read_video(_VIDEO.value)
  fps = _FPS.value or file_fps
  if not fps > 0:
    raise app.UsageError(f"{_VIDEO.value} does not give its frame rate: pass --fps")
  intrinsics, camera_from_world = files.read_camera(_CAMERA.value)
  size = files.read_image_size(_CAMERA.value)
  if size is not None and size != (frames.shape[2], frames.shape[1]):
    raise files.VideoFileError(
        f"{_VIDEO.value} is {frames.shape[2]}x{frames.shape[1]} pixels, {_CAMERA.value} was "
        f"calibrated at {size[0]}x{size[1]}: calibrate at the resolution the camera films at")
  distortion = files.read_distortion(_CAMERA.value)
  if distortion is not None:  # the tracker's PnP is a pinhole camera's
    frames = files.undistort(frames, intrinsics, distortion)
  stickers, initial_pose = files.read_stickers(_STICKERS.value)
  traj = track_poses(frames, intrinsics, camera_from_world, stickers, initial_pose, fps=fps,
                     push_time=_PUSH_TIME.value, steps=_STEPS.value or None,
                     smoothing=_SMOOTHING.value, exposure=_EXPOSURE.value, progress=True)
  os.makedirs(os.path.dirname(os.path.abspath(_OUT.value)), exist_ok=True)
  np.savez(_OUT.value, trajectory=traj, dt=np.float64(TIMESTEP),
           initial_pose=np.asarray(initial_pose, np.float64))
  print(f"{len(frames)} frames at {fps:g} fps -> {len(traj)} poses at dt {TIMESTEP:.5f} s: "
        f"{_OUT.value}")


if __name__ == "__main__":
  app.run(main)
