"""Rendered videos as hard as real ones (paper Sec. 5.3 has real ones; here there are
none): a tower with red stickers on its blocks, filmed at any frame rate with motion
blur, sensor noise, lighting change and occlusion.

The camera looks along the dataset camera's line of sight from DISTANCE_SCALE of its
distance with its own field of view (FOVY). Stickers are 3 cm red squares, 0.5 mm thick,
at the four corners of the two side faces of each block that face the camera (the
"sides" layout; "sides_top" adds the top faces, "all" every face: STICKER_LAYOUTS), a
sticker side in from each edge, so their centres are known points of the object frame.
Motion blur averages `shutter_samples` renders spread over the exposure; the other
degradations act on the blurred frames (`degrade`).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from ppdjax.conventions import NUM_SLOTS  # noqa: E402
from ppdjax.dataset import camera, render  # noqa: E402
from ppdjax.video import pose as posemod  # noqa: E402

STICKER_HALF = 0.015  # m: half the side of a square sticker
STICKER_THICKNESS = 0.0005  # m: thin, so its sides hardly show
# The video camera looks along the dataset camera's line of sight from DISTANCE_SCALE of
# its distance to the target, with a field of view of FOVY degrees.
DISTANCE_SCALE = 1.0
FOVY = 30.0
# the shutter stays open for half of each frame period, ending at the frame's time
EXPOSURE = 0.5
CORNERS = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)], np.float64)


# The faces that carry stickers, as (axis, sign) of the face normal in the block frame:
# "sides", the two side faces the camera sees (-y and +x; it looks from the front right);
# "sides_top" adds the top faces, whose stickers a tower falling away from the camera
# turns towards it while it hides the sides (a sticker another block covers is left off);
# "all" puts them on all six faces, for towers that tumble and show any face.
STICKER_LAYOUTS = {"sides": ((1, -1.0), (0, 1.0)),
                   "sides_top": ((1, -1.0), (0, 1.0), (2, 1.0)),
                   "all": ((1, -1.0), (0, 1.0), (2, 1.0), (1, 1.0), (0, -1.0), (2, -1.0))}
STICKER_FACES = STICKER_LAYOUTS["sides"]
_FACE_QUATS = {(1, -1.0): (np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0),  # local z -> -y
               (0, 1.0): (np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0),  # local z -> +x
               (2, 1.0): (1.0, 0.0, 0.0, 0.0),  # local z -> +z
               (1, 1.0): (np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0),  # local z -> +y
               (0, -1.0): (np.sqrt(0.5), 0.0, -np.sqrt(0.5), 0.0),  # local z -> -x
               (2, -1.0): (0.0, 1.0, 0.0, 0.0)}  # local z -> -z


def _quat_mul(a, b):
  w1, x1, y1, z1 = a
  w2, x2, y2, z2 = b
  return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                   w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def sticker_layout(half_size: np.ndarray, pos: np.ndarray, quat: np.ndarray,
                   valid: np.ndarray, faces=STICKER_FACES) -> tuple[np.ndarray, np.ndarray]:
  """(N, 3) sticker centres in the object frame and (N, 4) their orientations: on each
  valid block's `faces` (a `STICKER_LAYOUTS` value), one at each corner of the face,
  inset by a sticker side; none where another block covers the spot."""
  if tuple(faces) not in STICKER_LAYOUTS.values():
    raise ValueError(f"faces must be one of STICKER_LAYOUTS {sorted(STICKER_LAYOUTS)}, got "
                     f"{faces!r}")
  blocks = [(posemod.pose_to_matrix(np.concatenate([p, q]))[:3, :3], p, q, h)
            for h, p, q, v in zip(half_size, pos, quat, valid) if v]
  covered = lambda c, me: any(  # noqa: E731
      np.all(np.abs(r.T @ (c - p)) <= h + STICKER_THICKNESS)
      for j, (r, p, _, h) in enumerate(blocks) if j != me)
  centres, quats = [], []
  for i, (rot, p, q, h) in enumerate(blocks):
    for axis, sign in faces:
      others = [a for a in range(3) if a != axis]
      for s1 in (-1, 1):
        for s2 in (-1, 1):
          local = np.zeros(3)
          local[axis] = sign * (h[axis] + STICKER_THICKNESS / 2)
          local[others[0]] = s1 * (h[others[0]] - 2 * STICKER_HALF)
          local[others[1]] = s2 * (h[others[1]] - 2 * STICKER_HALF)
          centre = rot @ local + p
          if not covered(centre, i):
            centres.append(centre)
            quats.append(_quat_mul(q, _FACE_QUATS[(axis, sign)]))
  return np.array(centres).reshape(-1, 3), np.array(quats).reshape(-1, 4)


def intrinsics(height: int, width: int, fovy: float = FOVY) -> np.ndarray:
  """(3, 3) K of the video camera in OpenCV's pixel convention (pixel centres at integer
  coordinates, so the centre of a W x H frame is at ((W - 1) / 2, (H - 1) / 2))."""
  f = 0.5 * height / np.tan(np.radians(fovy) / 2)
  return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


MAX_FRAME = 1280  # pixels: the video scene's offscreen buffer, each side


def check_view(height: int, width: int, fovy: float, stickers: str) -> None:
  """ValueError naming a frame, field of view or sticker layout `VideoRenderer` cannot
  film (checked where it is asked for: a worker process failing to start hangs a pool)."""
  if stickers not in STICKER_LAYOUTS:
    raise ValueError(f"stickers must be one of {sorted(STICKER_LAYOUTS)}, got {stickers!r}")
  if not (isinstance(fovy, (int, float)) and 0 < fovy < 180):
    raise ValueError(f"fovy must lie in (0, 180) degrees, got {fovy!r}")
  if not (16 <= height <= MAX_FRAME and 16 <= width <= MAX_FRAME):
    raise ValueError(f"image size must be within 16..{MAX_FRAME} pixels a side, got "
                     f"{height}x{width}")


class VideoRenderer(render.SlotRenderer):
  """Renders a K-slot object at given poses, with its stickers, from the video camera."""

  def __init__(self, height: int = 480, width: int = 640, num_slots: int = NUM_SLOTS,
               fovy: float = FOVY, distance_scale: float = DISTANCE_SCALE,
               stickers: str = "sides"):
    check_view(height, width, fovy, stickers)
    self.faces = STICKER_LAYOUTS[stickers]
    self.PER_BLOCK = 4 * len(self.faces)  # pylint: disable=invalid-name
    boxes = render.box_geoms(num_slots)
    sticker_xml = "\n".join(
        f'      <geom name="sticker{i}" type="box" size="{STICKER_HALF} {STICKER_HALF} '
        f'{STICKER_THICKNESS / 2}" material="sticker" pos="0.01 {0.001 * i} 0.03" '
        f'quat="0.9 0.1 0.2 0.3"/>' for i in range(self.PER_BLOCK * num_slots))
    sticker_asset = ('    <material name="sticker" rgba="0.9 0.02 0.02 1" specular="0.1" '
                     'emission="0.3"/>')
    xml = render.stage_xml(render.material_assets(num_slots), boxes + "\n" + sticker_xml,
                           sticker_asset)
    xml = xml.replace('offwidth="1024" offheight="1024"',
                      f'offwidth="{MAX_FRAME}" offheight="{MAX_FRAME}"')
    eye = camera.CAMERA_TARGET + distance_scale * (camera.CAMERA_POS - camera.CAMERA_TARGET)
    xml = xml.replace(f'fovy="{camera.FOVY}"', f'fovy="{fovy}"').replace(
        'pos="' + " ".join(f"{v}" for v in camera.CAMERA_POS) + '"',
        'pos="' + " ".join(f"{v}" for v in eye) + '"')
    super().__init__(xml, height, width, num_slots)
    self.intrinsics = intrinsics(height, width, fovy)
    self.camera_from_world = camera.camera_from_world()
    self.camera_from_world[:3, 3] = -self.camera_from_world[:3, :3] @ eye
    self._sticker0 = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "sticker0")

  def set_object(self, prims, material_ids, texture_seeds) -> np.ndarray:
    """Writes one object (numpy Primitives fields, K slots) and returns its (N, 3)
    sticker centres in the object frame."""
    m, k = self.model, self.num_slots
    self.write_object(prims, material_ids, texture_seeds)
    valid = np.asarray(prims.valid).astype(bool)
    quat = np.asarray(prims.quat) / np.linalg.norm(prims.quat, axis=-1, keepdims=True)
    points, orient = sticker_layout(np.asarray(prims.half_size), np.asarray(prims.pos), quat,
                                    valid, self.faces)
    total = self.PER_BLOCK * k
    s = slice(self._sticker0, self._sticker0 + total)
    m.geom_pos[s] = np.concatenate([points, np.zeros((total - len(points), 3))])
    m.geom_quat[s] = np.concatenate([orient, np.tile([1.0, 0, 0, 0], (total - len(points), 1))])
    m.geom_group[s] = np.where(np.arange(total) < len(points), 0, render.HIDDEN_GROUP)
    return points

  def render(self, pose7: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 frame with the object frame at world pose (7,)."""
    self.model.body_pos[1], self.model.body_quat[1] = pose7[:3], pose7[3:]
    mujoco.mj_forward(self.model, self.data)
    self._renderer.update_scene(self.data, camera="view")
    return self._renderer.render().copy()


def film(renderer: VideoRenderer, rest_pose: np.ndarray, trajectory: np.ndarray, dt: float,
         fps: float, shutter_samples: int = 3, exposure: float = EXPOSURE) -> np.ndarray:
  """(F, H, W, 3) uint8 frames at i / fps, i < F, of an object at rest until time 0 and
  then along `trajectory` ((T, 7), step k at (k + 1) dt): each frame averages
  `shutter_samples` renders at the middles of equal parts of the `exposure` / fps seconds
  before it (so that, as with a real shutter, it shows the object on average
  `exposure` / (2 fps) before the frame's time: `track_poses(exposure=...)`)."""
  times = np.concatenate([[0.0], dt * np.arange(1, len(trajectory) + 1)])
  poses = np.concatenate([rest_pose[None], trajectory])
  count = int(np.floor(times[-1] * fps + 1e-9)) + 1
  parts = (np.arange(shutter_samples) + 0.5) / shutter_samples
  frames = []
  for i in range(count):
    t = i / fps - exposure / fps * parts[::-1]
    at = posemod.resample(times, poses, np.clip(t, 0.0, times[-1]))
    frames.append(np.mean([renderer.render(p) for p in at], 0))
  return np.round(np.stack(frames)).astype(np.uint8)


def degrade(frames: np.ndarray, rng: np.random.Generator, *, noise: float = 0.0,
            lighting: float = 0.0, occlusion: float = 0.0) -> np.ndarray:
  """Frames as a real camera would give them: Gaussian sensor noise of `noise` grey
  levels, a brightness drifting by up to +-`lighting` (a fraction) over the clip, and a
  grey bar `occlusion` of the frame's width wide sweeping across it (0: none)."""
  out = frames.astype(np.float32)
  n, h, w = frames.shape[:3]
  if lighting:
    phase = rng.uniform(0, 2 * np.pi)
    gain = 1.0 + lighting * np.sin(phase + np.linspace(0, 2 * np.pi, n))
    out *= gain[:, None, None, None]
  if occlusion:
    bar = int(occlusion * w)
    for i in range(n):
      x0 = int((i / max(n - 1, 1)) * (w + bar)) - bar
      out[i, :, max(x0, 0):max(x0 + bar, 0)] = 90.0
  if noise:
    out += rng.normal(0.0, noise, out.shape)
  return np.clip(np.round(out), 0, 255).astype(np.uint8)
