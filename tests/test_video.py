"""ppdjax.video on synthetic frames: red stickers drawn at their true projections."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ppdjax.conventions import TIMESTEP
from ppdjax.metrics import relative_rotation
from ppdjax.video import TrackingError, detect_stickers, solve_pnp, track_poses
from ppdjax.video import pose as posemod

W, H, FPS = 640, 480, 60.0
K = np.array([[600.0, 0, W / 2], [0, 600.0, H / 2], [0, 0, 1]])
# the 8 corners of a 0.2 x 0.2 x 0.4 m block (object frame at its centre)
STICKERS = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.2, 0.2)])


def look_at(eye, target):
  f = (target - eye) / np.linalg.norm(target - eye)
  r = np.cross(f, [0.0, 0.0, 1.0])
  r /= np.linalg.norm(r)
  rot = np.stack([r, np.cross(f, r), f])
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = rot, -rot @ eye
  return m


CAMERA = look_at(np.array([0.3, -1.6, 0.7]), np.array([0.0, 0.0, 0.2]))


def true_pose(t):
  """The block slides along x at 0.5 m/s and turns about z at 2 rad/s, from rest at t < 0."""
  t = max(t, 0.0)
  q = Rotation.from_rotvec([0, 0, 2.0 * t]).as_quat(scalar_first=True)
  return np.concatenate([[0.5 * t, 0.0, 0.2], q])


def render(pose, hidden=(), noise=0.0, rng=None):
  img = np.full((H, W, 3), 120, np.uint8)
  uv, _ = posemod.project(STICKERS, CAMERA @ posemod.pose_to_matrix(pose), K)
  for i, (u, v) in enumerate(uv):
    if i not in hidden:
      cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 5 * 16, (220, 30, 30), -1,
                 cv2.LINE_AA, shift=4)
  if noise:
    img = np.clip(img + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)
  return img, uv


def clip(n=30, hidden=lambda t: (), noise=0.0, start=0.0):
  rng = np.random.default_rng(0)
  return np.stack([render(true_pose(i / FPS - start), hidden(i), noise, rng)[0]
                   for i in range(n)])


def errors(traj, start=0.0):
  times = start + TIMESTEP * np.arange(1, len(traj) + 1)
  true = np.stack([true_pose(t - start) for t in times])
  pos_mm = 1e3 * np.linalg.norm(traj[:, :3] - true[:, :3], axis=-1)
  return pos_mm, np.degrees(np.linalg.norm(relative_rotation(traj[:, 3:], true[:, 3:]), axis=-1))


def test_detection_finds_each_sticker_to_a_tenth_of_a_pixel():
  img, uv = render(true_pose(0.1))
  det = detect_stickers(img)
  assert len(det) == len(STICKERS)
  gaps = np.linalg.norm(det[:, None] - uv[None], axis=-1).min(0)
  assert gaps.max() < 0.1, gaps


def test_brick_and_large_red_surfaces_are_not_stickers():
  img = np.full((H, W, 3), 120, np.uint8)
  img[50:150, 50:250] = (158, 56, 36)  # the brick texture's base colour (saturation 196)
  img[200:440, 300:620] = (230, 20, 20)  # a red surface far larger than a sticker
  cv2.circle(img, (100, 300), 5, (220, 30, 30), -1)
  det = detect_stickers(img)
  np.testing.assert_allclose(det, [[100.0, 300.0]], atol=0.05)


def test_matching_assigns_by_minimum_total_distance_within_the_gate():
  predicted = np.array([[0.0, 0.0], [10.0, 0.0], [100.0, 100.0]])
  detections = np.array([[9.0, 0.0], [1.0, 0.0]])  # greedy nearest would pair 1 with 0
  which = posemod.match(detections, predicted, np.ones(3, bool), gate=5.0)
  np.testing.assert_array_equal(which, [1, 0, -1])


def test_pnp_recovers_a_pose_from_a_rough_guess():
  truth = CAMERA @ posemod.pose_to_matrix(true_pose(0.3))
  uv, _ = posemod.project(STICKERS, truth, K)
  guess = truth.copy()
  guess[:3, :3] = Rotation.from_rotvec([0.1, -0.05, 0.1]).as_matrix() @ truth[:3, :3]
  guess[:3, 3] += [0.05, -0.03, 0.1]
  np.testing.assert_allclose(solve_pnp(STICKERS, uv, K, guess), truth, atol=1e-6)


def test_track_poses_recovers_the_trajectory_at_the_simulators_dt():
  traj = track_poses(clip(noise=4.0), K, CAMERA, STICKERS, true_pose(0.0), fps=FPS)
  assert traj.shape == (int(29 / FPS / TIMESTEP), 7) and traj.dtype == np.float32
  pos_mm, rot_deg = errors(traj)
  assert np.median(pos_mm) < 2.0 and np.median(rot_deg) < 0.5, (pos_mm, rot_deg)


def test_stickers_that_vanish_and_reappear_are_followed():
  """Two stickers gone in frames 8-15, all of them in frames 20-21 (33 ms); the push
  starts 0.1 s into the video."""
  def hidden(i):
    return (0, 5) if 8 <= i <= 15 else tuple(range(8)) if 20 <= i <= 21 else ()
  traj = track_poses(clip(36, hidden, start=0.1), K, CAMERA, STICKERS, true_pose(0.0),
                     fps=FPS, push_time=0.1, steps=128, smoothing=0.5)
  pos_mm, rot_deg = errors(traj, start=0.1)
  assert traj.shape == (128, 7)
  assert pos_mm.max() < 10.0 and np.median(pos_mm) < 2.0, pos_mm


def test_stickers_lost_for_too_long_raise_an_error_naming_the_frames():
  frames = clip(30, lambda i: tuple(range(8)) if 10 <= i <= 19 else ())
  with pytest.raises(TrackingError, match="frames 10-19"):
    track_poses(frames, K, CAMERA, STICKERS, true_pose(0.0), fps=FPS)


@pytest.mark.parametrize("change, message", [
    (dict(frames=np.zeros((4, 8, 8, 3), np.float32)), "uint8"),
    (dict(frames=np.zeros((4, 8, 8), np.uint8)), r"\(T, H, W, 3\)"),
    (dict(stickers=STICKERS[:3]), "N >= 4"),
    (dict(intrinsics=np.full((3, 3), np.nan)), "intrinsics"),
    (dict(camera_from_world=2 * np.eye(4)), "orthonormal"),
    (dict(initial_pose=np.zeros(7)), "unit quaternion"),
    (dict(steps=10_000), "covers"),
])
def test_bad_input_is_named(change, message):
  args = dict(frames=clip(4), intrinsics=K, camera_from_world=CAMERA, stickers=STICKERS,
              initial_pose=true_pose(0.0))
  steps = change.pop("steps", None)
  args.update(change)
  with pytest.raises(ValueError, match=message):
    track_poses(**args, fps=FPS, steps=steps)


@pytest.mark.parametrize("frame, fovy", [((480, 640), 30.0), ((960, 1280), 42.0)])
def test_rendered_tower_stickers_give_its_rest_pose(frame, fovy):
  """ppdjax.video.synthetic: a 3-block stone tower at rest, rendered with its stickers by
  the video camera (the default view and the video preset's wider, larger one): the
  stickers found in the frame, matched at the true pose, give that pose back to a few
  millimetres (the camera model matches the renderer's pixels)."""
  import jax
  import jax.numpy as jnp
  from ppdjax.dataset import towers
  from ppdjax.sim import scene
  from ppdjax.dataset.materials import MATERIAL_NAMES
  from ppdjax.video import synthetic
  tower = jax.tree.map(lambda a: np.asarray(a[0]), towers.sample_towers(21, 1))
  rest = np.concatenate([np.asarray(scene.rest_position(jax.tree.map(jnp.asarray, tower))),
                         [1.0, 0.0, 0.0, 0.0]])
  with synthetic.VideoRenderer(*frame, fovy=fovy) as r:
    points = r.set_object(tower, [MATERIAL_NAMES.index("stone")] * 5, np.zeros(5, int))
    image = r.render(rest)
    truth = r.camera_from_world @ posemod.pose_to_matrix(rest)
    uv, _ = posemod.project(points, truth, r.intrinsics)
    det = detect_stickers(image)
    which = posemod.match(det, uv, np.ones(len(points), bool), 2.0)
    ok = which >= 0
    assert ok.sum() >= 4
    assert np.median(np.linalg.norm(det[which[ok]] - uv[ok], axis=-1)) < 0.3
    solved = solve_pnp(points[ok], det[which[ok]], r.intrinsics, truth)
  world = np.linalg.inv(r.camera_from_world) @ solved
  assert np.linalg.norm(world[:3, 3] - rest[:3]) < 3e-3


def test_the_video_camera_names_a_bad_view_or_frame():
  """VideoRenderer: a field of view outside (0, 180) degrees, or a frame larger than the
  scene's offscreen buffer, is named, not rendered wrong."""
  from ppdjax.video import synthetic
  with pytest.raises(ValueError, match="fovy"):
    synthetic.VideoRenderer(240, 320, fovy=180.0)
  with pytest.raises(ValueError, match="image size"):
    synthetic.VideoRenderer(960, 1600)
  from ppdjax.video.observe import observe_towers  # pylint: disable=import-outside-toplevel
  with pytest.raises(ValueError, match="fovy"):  # before the workers start: no hung pool
    observe_towers(None, None, None, np.zeros((1, 7)), np.zeros((1, 300, 7)), steps=10,
                   fovy=0.0, workers=2)


def test_top_stickers_add_the_uncovered_top_corners_and_keep_the_sides():
  """synthetic.sticker_layout: "sides_top" keeps the "sides" stickers and adds the top
  faces' corners, but none on a spot another block covers; an unknown layout is named."""
  from ppdjax.video import synthetic
  half = np.array([[0.2, 0.1, 0.1], [0.1, 0.1, 0.1]])  # a narrow block on a wide one
  pos = np.array([[0.0, 0.0, 0.1], [-0.1, 0.0, 0.3]])
  quat = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
  valid = np.ones(2, bool)
  sides, _ = synthetic.sticker_layout(half, pos, quat, valid)
  both, q = synthetic.sticker_layout(half, pos, quat, valid,
                                     synthetic.STICKER_LAYOUTS["sides_top"])
  assert len(sides) == 16 and np.allclose(both[:8], sides[:8])
  top = both[np.isclose(both[:, 2], 0.2 + synthetic.STICKER_THICKNESS / 2)]
  # the wide block's top: its two corners at x = +0.17 are free, those at x = -0.17 lie
  # under the narrow block (x in [-0.2, 0])
  assert len(top) == 2 and np.allclose(top[:, 0], 0.17)
  assert len(both) == 16 + 2 + 4 and q.shape == (22, 4)
  # every face: 4 side faces of 4 corners on each block, the tops as above, the wide
  # block's bottom (on the ground) but not the narrow one's (on the wide block's top)
  every, q = synthetic.sticker_layout(half, pos, quat, valid, synthetic.STICKER_LAYOUTS["all"])
  assert len(every) == 2 * 16 + (2 + 4) + (4 + 0) and q.shape == (42, 4)
  for c, r in zip(every, q):  # each sticker's z axis is the outward normal of its face
    n = posemod.pose_to_matrix(np.concatenate([c, r]))[:3, 2]
    out = [(c - p) @ n - np.abs(n) @ h for h, p in zip(half, pos)]
    assert np.isclose(min(out, key=abs), synthetic.STICKER_THICKNESS / 2), (c, n)
  with pytest.raises(ValueError, match="STICKER_LAYOUTS"):
    synthetic.sticker_layout(half, pos, quat, valid, ((2, -1.0),))


def test_track_command_on_a_short_clip(tmp_path):
  """python -m ppdjax.track on a lossless .avi of the synthetic block at 60 fps."""
  import json
  import os
  import subprocess
  import sys
  video = str(tmp_path / "clip.avi")
  writer = cv2.VideoWriter(video, cv2.VideoWriter_fourcc(*"FFV1"), FPS, (W, H))
  for frame in clip(noise=2.0):
    writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
  writer.release()
  (tmp_path / "camera.json").write_text(json.dumps(
      {"intrinsics": K.tolist(), "camera_from_world": CAMERA.tolist()}))
  (tmp_path / "stickers.json").write_text(json.dumps(
      {"stickers": STICKERS.tolist(), "initial_pose": true_pose(0.0).tolist()}))
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  run = subprocess.run([sys.executable, "-m", "ppdjax.track", f"--video={video}",
                        f"--camera={tmp_path / 'camera.json'}",
                        f"--stickers={tmp_path / 'stickers.json'}",
                        f"--out={tmp_path / 'traj.npz'}"], cwd=root, capture_output=True,
                       text=True, timeout=300, env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode == 0, run.stderr[-2000:]
  traj = np.load(tmp_path / "traj.npz")["trajectory"]
  pos_mm, rot_deg = errors(traj)
  assert len(traj) == int(29 / FPS / TIMESTEP) and np.median(pos_mm) < 2.0
  # python -m ppdjax.decompose --trajectory reads it in the simulator's convention
  from ppdjax.configs import video
  from ppdjax.video.files import tracked_observation
  config = video.get_config("tiny")
  config.data.steps = len(traj)
  obs = tracked_observation(str(tmp_path / "traj.npz"), config, 0.2)
  moved = posemod.relative_to_rest(traj, true_pose(0.0), np.array([0.0, 0.0, 0.2]))
  np.testing.assert_allclose(obs[0], moved)
  assert obs.shape == (1, len(traj), 7) and np.linalg.norm(obs[0, 0, :3] - [0, 0, 0.2]) < 0.02
  config.model.num_pushes = 4
  with pytest.raises(ValueError, match="reads 4 pushes"):
    tracked_observation(str(tmp_path / "traj.npz"), config, 0.2)


def test_relative_to_rest_forgets_where_the_object_stood():
  rng = np.random.default_rng(0)
  rest = np.array([0.0, 0.0, 0.3])
  local = np.concatenate([rest + rng.normal(0, 0.1, (20, 3)),
                          Rotation.random(20, random_state=1).as_quat(scalar_first=True)], 1)
  local[:, 3:] *= np.sign(local[:, 3:4])
  # the same motion filmed with the object standing elsewhere, turned about z
  where = np.eye(4)
  where[:3, :3] = Rotation.from_euler("z", 0.7).as_matrix()
  where[:3, 3] = [1.2, -0.4, 0.0]
  shift = lambda p: posemod.matrix_to_pose(where @ posemod.pose_to_matrix(p))  # noqa: E731
  world = np.stack([shift(p) for p in local])
  start = shift(np.concatenate([rest, [1.0, 0, 0, 0]]))
  np.testing.assert_allclose(posemod.relative_to_rest(world, start, rest), local, atol=1e-5)


def test_tracked_trajectory_files_name_their_problems(tmp_path):
  from ppdjax.video import files
  with pytest.raises(ValueError, match="no such trajectory"):
    files.read_trajectory(str(tmp_path / "none.npz"))
  good = dict(trajectory=np.zeros((5, 7)), dt=TIMESTEP, initial_pose=np.zeros(7))
  for change, message in [({"dt": 0.01}, "dt is 0.01"), ({"initial_pose": np.zeros(3)},
                                                         "expected trajectory"),
                          ({"trajectory": np.full((5, 7), np.nan)}, "NaN")]:
    np.savez(tmp_path / "t.npz", **{**good, **change})
    with pytest.raises(ValueError, match=message):
      files.read_trajectory(str(tmp_path / "t.npz"))
  np.savez(tmp_path / "t.npz", trajectory=np.zeros((5, 7)))
  with pytest.raises(ValueError, match="missing dt, initial_pose"):
    files.read_trajectory(str(tmp_path / "t.npz"))


def test_track_files_name_their_problems(tmp_path):
  from ppdjax.video import files
  with pytest.raises(ValueError, match="no such video"):
    files.read_video(str(tmp_path / "none.mp4"))
  (tmp_path / "bad.mp4").write_bytes(b"not a video")
  with pytest.raises(ValueError, match="not a readable video"):
    files.read_video(str(tmp_path / "bad.mp4"))
  (tmp_path / "cam.json").write_text('{"intrinsics": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}')
  with pytest.raises(ValueError, match="missing camera_from_world"):
    files.read_camera(str(tmp_path / "cam.json"))
  (tmp_path / "st.json").write_text("{oops")
  with pytest.raises(ValueError, match="not valid JSON"):
    files.read_stickers(str(tmp_path / "st.json"))


@pytest.mark.slow  # ~28 s on 2 cores: `make test-all`; the shipped example's clip is
# tracked in the default tests (test_video_setup)
def test_a_struck_real_tower_filmed_and_tracked(tmp_path):
  """The real towers' setup end to end on a short clip: a pine and copper tower struck by
  the pendulum (MuJoCo C), rendered with its stickers and degraded
  (`video.observe.observe_towers`), tracked back to millimetres; the same frames through
  `python -m ppdjax.track` as a lossless .avi give the same trajectory."""
  import json
  import os
  import subprocess
  import sys

  import jax
  import jax.numpy as jnp

  import ppdjax
  from ppdjax.dataset import materials, towers
  from ppdjax.sim import scene
  from ppdjax.sim.pushes import pendulum_strike
  from ppdjax.video import synthetic
  from ppdjax.video.observe import observe_towers
  half, pos, quat = towers.sample_geometry(np.random.default_rng(4), 2)
  tower = ppdjax.primitives.make(half, pos, quat, [500.0, 9000.0], 5)
  ids = np.array([[materials.ALL_MATERIAL_NAMES.index(m) for m in ("pine", "copper")]
                  + [0] * 3])
  steps = 48
  truth = np.asarray(ppdjax.simulate(tower, pendulum_strike(), steps=steps + 12,
                                     backend="mujoco"))[0]
  rest = np.concatenate([np.asarray(scene.rest_position(jax.tree.map(jnp.asarray, tower))),
                         [1.0, 0.0, 0.0, 0.0]])
  batch = jax.tree.map(lambda a: np.asarray(a)[None], tower)
  tracked, errors = observe_towers(batch, ids, np.zeros_like(ids), rest[None], truth[None],
                                   steps=steps, frame=(480, 640), seed=3, progress=False)
  assert errors == [None]
  gap_mm = 1e3 * np.linalg.norm(tracked[0, :, :3] - truth[:steps, :3], axis=-1)
  assert np.linalg.norm(truth[steps - 1, :3] - rest[:3]) > 0.05  # it moved
  assert np.median(gap_mm) < 4.0, np.median(gap_mm)
  with synthetic.VideoRenderer(480, 640) as r:  # the same clip through the command line
    points = r.set_object(tower, ids[0], np.zeros(5, int))
    frames = synthetic.degrade(synthetic.film(r, rest, truth, TIMESTEP, 60.0),
                               np.random.default_rng([3, 0]), noise=3.0, lighting=0.1)
    intrinsics, camera = r.intrinsics, r.camera_from_world
  video = str(tmp_path / "clip.avi")
  writer = cv2.VideoWriter(video, cv2.VideoWriter_fourcc(*"FFV1"), 60.0, (640, 480))
  for frame in frames:
    writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
  writer.release()
  (tmp_path / "camera.json").write_text(json.dumps(
      {"intrinsics": intrinsics.tolist(), "camera_from_world": camera.tolist()}))
  (tmp_path / "stickers.json").write_text(json.dumps(
      {"stickers": points.tolist(), "initial_pose": rest.tolist()}))
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  run = subprocess.run([sys.executable, "-m", "ppdjax.track", f"--video={video}",
                        f"--camera={tmp_path / 'camera.json'}",
                        f"--stickers={tmp_path / 'stickers.json'}", f"--steps={steps}",
                        f"--exposure={synthetic.EXPOSURE}",
                        f"--out={tmp_path / 'traj.npz'}"], cwd=root, capture_output=True,
                       text=True, timeout=300, env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode == 0, run.stderr[-2000:]
  np.testing.assert_allclose(np.load(tmp_path / "traj.npz")["trajectory"], tracked[0],
                             atol=1e-4)



def test_the_lookalike_report_reads_the_motion_against_the_look(tmp_path):
  """video_lookalike.extend_report on made-up towers: two painted 2-block towers of one
  shape, one heavy on top and one light; the full model reads them right, the
  appearance-only one reads both alike. Its keys, figure and section follow."""
  import json  # pylint: disable=import-outside-toplevel
  from types import SimpleNamespace  # pylint: disable=import-outside-toplevel
  from ppdjax.configs import video as video_config  # pylint: disable=import-outside-toplevel
  from ppdjax.reproduce import video_lookalike  # pylint: disable=import-outside-toplevel

  n, k, t = 4, 5, 8
  valid = np.zeros((n, k), bool)
  valid[:, :2] = True
  pos = np.zeros((n, k, 3), np.float32)
  pos[:, 1, 2] = 0.2
  half = np.full((n, k, 3), 0.1, np.float32)
  dens = np.zeros((n, k), np.float32)
  dens[:, :2] = [[500, 7900], [7900, 500], [2700, 9000], [9000, 2700]]
  traj = np.zeros((n, t, 7), np.float32)
  traj[..., 3] = 1.0
  traj[:, :, 0] = np.linspace(0, 1, t)[None] * np.arange(1, n + 1)[:, None]
  test = {"valid": valid, "pos": pos, "half_size": half, "density": dens,
          "materials": np.where(valid, 5, -1), "image": np.zeros((n, 16, 16, 3), np.uint8),
          "tracked_trajectory": traj, "true_trajectory": traj,
          "errors": np.asarray([""] * n)}
  np.savez(tmp_path / "test.npz", **test)

  def decomposition(density):
    quat = np.zeros((n, k, 4), np.float32)
    quat[..., 0] = 1
    fields = {"pos": pos, "half_size": half, "quat": quat, "density": density,
              "valid": valid, "score": np.zeros(n, np.float32)}
    return {f"{way}_{f}": v for way in ("tracked", "true") for f, v in fields.items()}
  np.savez(tmp_path / "full.npz", **decomposition(dens))
  np.savez(tmp_path / "look.npz", **decomposition(np.where(valid, 3000.0, 0.0)))
  config = video_config.get_config("lookalike_tiny")
  pipe = SimpleNamespace(config=config, test_file=str(tmp_path / "test.npz"),
                         eval_files={"sample": str(tmp_path / "full.npz"),
                                     "refine": str(tmp_path / "full.npz"),
                                     "appearance": str(tmp_path / "look.npz")})
  (tmp_path / "res").mkdir()
  (tmp_path / "res" / "video_lookalike.md").write_text("# report\n")
  result = {"density": {"tracked": {"rmse_all": 0.0, "rmse_2_blocks": 0.0}},
            "heavier": {}, "tracking": {"tracked": n, "clips": n, "position_mm_median": 1.0,
                                         "rotation_deg_median": 0.1}}
  keys = video_lookalike.extend_report(pipe, str(tmp_path / "res"), "video_lookalike", result)
  assert keys["heavier_right"] == 100.0 and keys["pearson_r"] == pytest.approx(1.0)
  assert keys["heavier_towers"] == n and keys["appearance_only_rmse"] > 20
  saved = json.loads((tmp_path / "res" / "video_lookalike.json").read_text())
  for key in ("rmse_all", "rmse_2", "appearance_only_rmse", "heavier_right", "pearson_r",
              "tracked", "towers", "median_mm", "median_deg"):
    assert key in saved
  assert sorted(saved["twins"]) in ([0, 1], [2, 3], [0, 3], [1, 2], [0, 2], [1, 3])
  assert (tmp_path / "res" / "video_lookalike_twins.png").exists()
  assert "the motion against the look" in (tmp_path / "res" / "video_lookalike.md").read_text()


def test_the_lookalike_report_names_the_search_studys_latest_choice(tmp_path):
  """validation_summary reads video_search's later question (refine.starts, its own
  baseline) where the study holds one, and its first question (rounds, against the
  validation pipeline's +Refine) where it does not; the report's words follow."""
  import json  # pylint: disable=import-outside-toplevel
  from ppdjax.reproduce import video_report  # pylint: disable=import-outside-toplevel
  val = {"seed": 7, "decompose": {"refine": True},
         "density": {"tracked": {"rmse_all": 12.0}, "tracked, +Sample only": {"rmse_all": 15.0}}}
  (tmp_path / "video_lookalike_val.json").write_text(json.dumps(val))
  rows = lambda **r: {"rows": {k: {"rmse_all": v} for k, v in r.items()}}  # noqa: E731
  study = {"validation": rows(pipeline_refine=12.0, shells8=8.7, shells8_before_refinement=9.9),
           "chosen": "shells8"}
  (tmp_path / "video_search.json").write_text(json.dumps(study))
  first = video_report.validation_summary(str(tmp_path), "video_lookalike")["search"]
  assert first["chosen"] == "shells8" and first["against"] == "pipeline_refine"
  assert "8.7 for the chosen shells8 against the pipeline's 12.0" in video_report._search_words(
      first)
  study["starts"] = {"validation": rows(shells8=9.0, starts8=6.5), "chosen": "starts8",
                     "baseline": "shells8"}
  (tmp_path / "video_search.json").write_text(json.dumps(study))
  later = video_report.validation_summary(str(tmp_path), "video_lookalike")["search"]
  assert later["chosen"] == "starts8" and later["density_rmse_tracked"] == {
      "shells8": 9.0, "starts8": 6.5}
  assert "6.5 for the chosen starts8 against 9.0 for shells8" in video_report._search_words(later)
  assert video_report.validation_summary(str(tmp_path), "video_lookalike_val") is None


def test_the_report_says_how_many_starts_were_refined():
  """One start: the closest candidate refined; several: each refined, the closest kept;
  no refinement: the closest alone, whatever refine_starts says."""
  from ppdjax.reproduce import video_report  # pylint: disable=import-outside-toplevel
  words = video_report._refine_words  # pylint: disable=protected-access
  assert words({"refine": True, "refine_starts": 1}) == (
      "the closest by trajectory refined by Levenberg-Marquardt")
  assert words({"refine": True, "refine_starts": 8}).startswith("the 8 closest distinct")
  assert words({"refine": False, "refine_starts": 8}) == "the closest by trajectory"
