"""Objects observed as the paper's real towers were: filmed with red stickers, degraded
as a real camera would, and tracked back into trajectories (many at once, in processes)."""

from __future__ import annotations

import jax
import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import TIMESTEP
from ppdjax.dataset import render
from ppdjax.video import synthetic
from ppdjax.video.track import TrackingError, track_poses

_RENDERER = None  # one VideoRenderer per worker process


def _init(height: int, width: int, stickers: str, fovy: float) -> None:
  global _RENDERER
  _RENDERER = synthetic.VideoRenderer(height, width, fovy=fovy, stickers=stickers)


def _observe_one(job) -> tuple[np.ndarray | None, str | None]:
  (prims, mats, seeds, rest, truth, fps, steps, seed, degrade) = job
  points = _RENDERER.set_object(prims, mats, seeds)
  frames = synthetic.film(_RENDERER, rest, truth, TIMESTEP, fps)
  video = synthetic.degrade(frames, np.random.default_rng(seed), **degrade)
  try:
    return track_poses(video, _RENDERER.intrinsics, _RENDERER.camera_from_world, points, rest,
                       fps=fps, steps=steps, exposure=synthetic.EXPOSURE), None
  except TrackingError as e:
    return None, str(e)


def observe_towers(prims, material_ids, texture_seeds, rest_poses, trajectories, *,
                   steps: int, fps: float = 60.0, frame: tuple[int, int] = (480, 640),
                   noise: float = 3.0, lighting: float = 0.1, seed: int = 0,
                   stickers: str = "sides", fovy: float = synthetic.FOVY, workers: int = 0,
                   progress: bool = True):
  """Films each object along its true trajectory and tracks it back.

  Args:
    prims: numpy Primitives (B, K) in the object frame.
    material_ids, texture_seeds: (B, K) ints: what each block shows
      (`materials.LOOK_NAMES` ids; `materials.look_ids` of the materials) and its seed.
    rest_poses: (B, 7) world poses at rest; trajectories: (B, T, 7) world poses after each
      simulator step, a frame or more longer than `steps` (the last frame must lie at or
      beyond step `steps`).
    steps: simulator steps to recover per object.
    fps, frame: the camera's rate and (height, width); noise, lighting: `synthetic.degrade`.
    seed: clip i is degraded with the generator of (seed, i).
    stickers: the faces that carry stickers (`synthetic.STICKER_LAYOUTS`).
    fovy: the camera's vertical field of view, degrees (it looks from where it does).
    workers: processes (each with its own GL context); 0: this process.

  Returns:
    ((B, steps, 7) float32 tracked trajectories, NaN where tracking failed; a list of B
    failure messages or None).
  """
  b = len(rest_poses)
  if np.shape(trajectories)[:1] != (b,) or np.shape(trajectories)[2:] != (7,):
    raise ValueError(f"trajectories: expected shape ({b}, T, 7), got {np.shape(trajectories)}")
  synthetic.check_view(*frame, fovy, stickers)  # here, not in the pool's workers' start
  # the last frame shows the object half an exposure before its time
  last_frame = (np.floor(np.shape(trajectories)[1] * TIMESTEP * fps + 1e-9)
                - synthetic.EXPOSURE / 2) / fps
  if np.floor(last_frame / TIMESTEP + 1e-9) < steps:
    raise ValueError(f"trajectories of {np.shape(trajectories)[1]} steps are too short to film "
                     f"{steps} steps at {fps} fps: simulate at least one frame longer")
  degrade = {"noise": noise, "lighting": lighting}
  jobs = [(jax.tree.map(lambda a, i=i: np.asarray(a)[i], prims), np.asarray(material_ids)[i],
           np.asarray(texture_seeds)[i], np.asarray(rest_poses)[i],
           np.asarray(trajectories)[i], float(fps), int(steps), [seed, i], degrade)
          for i in range(b)]
  bar = tqdm(total=b, desc="film and track", unit="clip", disable=not progress)
  if workers > 0:
    with render.cpu_process_pool(workers, _init, (*frame, stickers, fovy)) as pool:
      results = []
      for r in pool.imap(_observe_one, jobs):
        results.append(r)
        bar.update()
  else:
    _init(*frame, stickers, fovy)
    try:
      results = []
      for job in jobs:
        results.append(_observe_one(job))
        bar.update()
    finally:
      _RENDERER.close()
  bar.close()
  tracked = np.full((b, steps, 7), np.nan, np.float32)
  for i, (traj, _) in enumerate(results):
    if traj is not None:
      tracked[i] = traj
  return tracked, [err for _, err in results]
