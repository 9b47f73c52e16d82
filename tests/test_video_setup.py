"""A user's video setup (docs/video.md): camera calibration from checkerboard photographs
(ppdjax.video.calibrate, python -m ppdjax.calibrate) on boards drawn by a known camera,
lens distortion and image size read by the tracker, and the shipped worked example."""

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from ppdjax.video import calibrate, files

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VIDEO_EXAMPLE = os.path.join(ROOT, "assets", "video_example")
BOARD, SQUARE = (9, 6), 0.03
K = np.array([[620.0, 0.0, 322.0], [0.0, 615.0, 236.0], [0.0, 0.0, 1.0]])
W, H, UP = 640, 480, 4  # drawn at 4x and averaged down: anti-aliased edges


def look_at(eye, target):
  """4x4 camera_from_world of a camera at `eye` looking at `target`, z up in the image's
  up direction (OpenCV axes: x right, y down, z forward)."""
  z = np.asarray(target, float) - eye
  z /= np.linalg.norm(z)
  x = np.cross(z, [0.0, 0.0, 1.0])
  x /= np.linalg.norm(x)
  y = np.cross(z, x)
  m = np.eye(4)
  m[:3, :3] = np.stack([x, y, z])
  m[:3, 3] = -m[:3, :3] @ eye
  return m


def draw_board(camera_from_board):
  """(H, W, 3) uint8: the board (with a white margin) as the camera K sees it."""
  big = np.full((H * UP, W * UP), 40, np.uint8)  # a dark room
  k = K.copy()
  k[:2] *= UP
  k[:2, 2] += (UP - 1) / 2  # pixel centres of the large image
  rvec = cv2.Rodrigues(camera_from_board[:3, :3])[0]
  tvec = camera_from_board[:3, 3]
  proj = lambda pts: cv2.projectPoints(np.asarray(pts, float), rvec, tvec, k, None)[0].reshape(
      -1, 2)
  cols, rows = BOARD
  margin = [[-2, -2, 0], [cols + 1, -2, 0], [cols + 1, rows + 1, 0], [-2, rows + 1, 0]]
  cv2.fillConvexPoly(big, np.round(proj(np.array(margin) * SQUARE) * 16).astype(np.int32),
                     255, cv2.LINE_AA, 4)
  for i in range(-1, cols):
    for j in range(-1, rows):
      if (i + j) % 2 == 0:
        sq = np.array([[i, j, 0], [i + 1, j, 0], [i + 1, j + 1, 0], [i, j + 1, 0]]) * SQUARE
        cv2.fillConvexPoly(big, np.round(proj(sq) * 16).astype(np.int32), 0, cv2.LINE_AA, 4)
  small = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
  return np.repeat(small[..., None], 3, -1)


def views():
  """Photographs of the board held at several tilts about 0.6 m from the camera."""
  out = []
  for ax, ay, dx in ((0.3, 0.0, 0.0), (-0.3, 0.2, 0.05), (0.1, -0.35, -0.05),
                     (0.4, 0.3, 0.0), (-0.2, -0.3, 0.03)):
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.array([ax, ay, 0.05]))[0]
    centre = np.array([(BOARD[0] - 1) / 2, (BOARD[1] - 1) / 2, 0.0]) * SQUARE
    m[:3, 3] = np.array([dx, 0.0, 0.6]) - m[:3, :3] @ centre
    out.append(draw_board(m))
  return out


def test_calibration_recovers_the_camera_and_the_table():
  """Intrinsics within 1 %; from four sides of the table: the camera's height within 5 mm
  and z up, the origin a corner of the board's inner grid, x and y along its rows and
  columns (which corner OpenCV lists first depends on the view; its order puts the board's
  z into the table seen from above, so y is mirrored to keep z up)."""
  cal = calibrate.calibrate_intrinsics(views(), BOARD, SQUARE)
  assert len(cal["views"]) == 5 and cal["rms_px"] < 0.5
  np.testing.assert_allclose(cal["intrinsics"], K, rtol=0.01, atol=2.0)
  centre = np.array([(BOARD[0] - 1) / 2, (BOARD[1] - 1) / 2, 0.0]) * SQUARE
  corners = [np.array([i, j, 0.0]) * SQUARE
             for i in (0, BOARD[0] - 1) for j in (0, BOARD[1] - 1)]
  eye = lambda m: np.linalg.inv(m)[:3, 3]
  mirrored = []  # whether OpenCV's own corner order put z into the table (the mirror branch)
  for angle in np.deg2rad([-80, 10, 100, 190]):
    truth = look_at(centre + [0.75 * np.cos(angle), 0.75 * np.sin(angle), 0.5], centre)
    image = draw_board(truth)
    got = calibrate.camera_from_ground(image, cal["intrinsics"], cal["distortion"],
                                       BOARD, SQUARE, image_size=(W, H))
    raw = calibrate._solve(  # pylint: disable=protected-access
        calibrate.board_points(BOARD, SQUARE), calibrate.find_board(image, BOARD),
        cal["intrinsics"], cal["distortion"])
    mirrored.append(bool(np.linalg.inv(raw)[2, 3] < 0))
    assert abs(eye(got)[2] - eye(truth)[2]) < 5e-3, (eye(got), eye(truth))
    board_from_world = np.linalg.inv(truth) @ got  # the found world in the board's frame
    np.testing.assert_allclose(board_from_world[:3, 2], [0, 0, 1], atol=0.01)  # z up
    assert min(np.linalg.norm(board_from_world[:3, 3] - c) for c in corners) < 5e-3
    x_axis = board_from_world[:3, 0]
    assert np.isclose(np.abs(x_axis).max(), 1.0, atol=0.01)  # along a row or a column
  assert all(mirrored), mirrored  # the branch that mirrors y ran in every view
  with pytest.raises(calibrate.CalibrationError, match="640x480 pixels, the calibration"):
    calibrate.camera_from_ground(draw_board(truth), K, np.zeros(5), BOARD, SQUARE,
                                 image_size=(1280, 720))


def test_calibrate_command_writes_what_track_reads(tmp_path):
  for i, image in enumerate(views()):
    cv2.imwrite(str(tmp_path / f"view{i}.png"), image)
  truth = look_at(np.array([-0.2, -0.6, 0.45]), [0.1, 0.1, 0.0])
  cv2.imwrite(str(tmp_path / "table.png"), draw_board(truth))
  out = tmp_path / "camera.json"
  run = subprocess.run([sys.executable, "-m", "ppdjax.calibrate",
                        f"--images={tmp_path}/view*.png", "--board=9x6", f"--square={SQUARE}",
                        f"--ground={tmp_path}/table.png", f"--out={out}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode == 0, run.stderr[-2000:]
  assert "found in 5 of 5" in run.stdout
  assert cv2.imread(str(tmp_path / "camera_axes.png")).shape == (H, W, 3)
  run = subprocess.run([sys.executable, "-m", "ppdjax.calibrate",
                        f"--images={tmp_path}/view0.png", "--board=9x6", f"--square={SQUARE}",
                        f"--ground={tmp_path}/table.png", f"--out={out}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode != 0 and "3 are needed" in run.stderr  # a usage error, named
  intrinsics, camera_from_world = files.read_camera(str(out))
  assert files.read_distortion(str(out)) is None or np.all(
      np.abs(files.read_distortion(str(out))) < 0.05)
  np.testing.assert_allclose(intrinsics, K, rtol=0.01, atol=2.0)
  assert abs(np.linalg.inv(camera_from_world)[2, 3] - 0.45) < 5e-3  # height above the table


def test_bad_photographs_are_named(tmp_path):
  blank = np.full((H, W, 3), 128, np.uint8)
  with pytest.raises(calibrate.CalibrationError, match="found in 1 of 3.*not found: b, c"):
    calibrate.calibrate_intrinsics([views()[0], blank, blank], BOARD, SQUARE,
                                   names=["a", "b", "c"])
  with pytest.raises(calibrate.CalibrationError, match="differ in size"):
    calibrate.calibrate_intrinsics([blank, blank[:100]], BOARD, SQUARE)
  with pytest.raises(calibrate.CalibrationError, match="square"):
    calibrate.calibrate_intrinsics([blank], BOARD, 0.0)
  with pytest.raises(calibrate.CalibrationError, match="no photographs"):
    calibrate.calibrate_intrinsics([], BOARD, SQUARE)
  with pytest.raises(calibrate.CalibrationError, match="table.png: the 9x6 board"):
    calibrate.camera_from_ground(blank, K, np.zeros(5), BOARD, SQUARE, name="table.png")
  with pytest.raises(files.MissingFileError, match="no such image"):
    files.read_image(str(tmp_path / "none.png"))
  (tmp_path / "bad.png").write_text("not an image")
  with pytest.raises(files.VideoFileError, match="not a readable image"):
    files.read_image(str(tmp_path / "bad.png"))
  cam = tmp_path / "camera.json"
  cam.write_text(json.dumps({"intrinsics": K.tolist(), "camera_from_world": np.eye(4).tolist(),
                             "distortion": [0.1, float("nan"), 0, 0, 0]}))
  with pytest.raises(files.VideoFileError, match="distortion must be 4 or 5 finite"):
    files.read_distortion(str(cam))


def test_undistorted_frames_are_what_a_pinhole_camera_sees():
  """A board drawn through a distorting lens, undistorted: its corners where the pinhole
  camera puts them (within 0.3 px)."""
  dist = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])
  m = np.eye(4)
  m[:3, 3] = [-0.12, -0.075, 0.5]
  pinhole = draw_board(m)
  # the distorted image: each output pixel reads the pinhole image where the lens sends it
  u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
  pts = np.stack([u.ravel(), v.ravel()], -1)[:, None]
  ideal = cv2.undistortPoints(pts, K, dist, P=K).reshape(H, W, 2)
  distorted = cv2.remap(pinhole, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR)
  back = files.undistort(distorted[None], K, dist)[0]
  a, b = calibrate.find_board(pinhole, BOARD), calibrate.find_board(back, BOARD)
  assert a is not None and b is not None
  assert np.abs(a - b).max() < 0.3



def test_the_shipped_video_example_tracks_back_to_its_truth(tmp_path):
  """docs/video.md's worked example as a user runs it: `python -m ppdjax.track` on the
  shipped clip, camera and stickers, told the shutter it was filmed with, gives the true
  trajectory within a few millimetres (ignoring the shutter delays every pose by a
  quarter of a frame), and the tower's mesh reads back as its named blocks."""
  from ppdjax.dataset.mesh_files import load_object  # pylint: disable=import-outside-toplevel
  with open(os.path.join(VIDEO_EXAMPLE, "truth.json")) as f:
    truth = json.load(f)
  median_mm = []
  for exposure in (truth["exposure"], 0.0):
    out = tmp_path / f"traj_{exposure}.npz"
    run = subprocess.run([sys.executable, "-m", "ppdjax.track",
                          f"--video={VIDEO_EXAMPLE}/clip.mp4",
                          f"--camera={VIDEO_EXAMPLE}/camera.json",
                          f"--stickers={VIDEO_EXAMPLE}/stickers.json",
                          f"--exposure={exposure}", f"--out={out}"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert run.returncode == 0, run.stderr[-2000:]
    tracked = np.load(out)["trajectory"]
    true = np.asarray(truth["true_trajectory"])[:len(tracked)]
    median_mm.append(np.median(1000 * np.linalg.norm(tracked[:, :3] - true[:, :3], axis=-1)))
    assert len(tracked) >= 200
  assert median_mm[0] < 1.5 and median_mm[1] > 1.5 * median_mm[0], median_mm
  tower, _ = load_object(os.path.join(VIDEO_EXAMPLE, "tower.glb"),
                         dict(zip(truth["blocks"], truth["materials"])))
  assert tower.names == tuple(truth["blocks"]) and tower.materials == tuple(truth["materials"])
  # a camera file calibrated at another size is refused, naming both
  with open(os.path.join(VIDEO_EXAMPLE, "camera.json")) as f:
    camera = {**json.load(f), "image_size": [1280, 720]}
  (tmp_path / "camera.json").write_text(json.dumps(camera))
  run = subprocess.run([sys.executable, "-m", "ppdjax.track",
                        f"--video={VIDEO_EXAMPLE}/clip.mp4", f"--camera={tmp_path}/camera.json",
                        f"--stickers={VIDEO_EXAMPLE}/stickers.json", f"--out={out}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode != 0 and "640x480 pixels" in run.stderr and "1280x720" in run.stderr


def test_a_tower_mesh_is_read_upright_from_the_towers_camera():
  """The shipped example's tower.glb read for a towers' model (`mesh_towers`): upright (the
  file's axes, pine below copper, 1 m largest extent), observed at the model's image size;
  read as a tool it is turned onto its principal axes."""
  from ppdjax import load_object  # pylint: disable=import-outside-toplevel
  from ppdjax.configs import video  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset.mesh_towers import observe_tower  # pylint: disable=import-outside-toplevel
  import trimesh  # pylint: disable=import-outside-toplevel

  path = os.path.join(ROOT, "assets", "video_example", "tower.glb")
  materials = {"block0": "pine", "block1": "copper"}
  tool, transform = load_object(path, part_materials=materials, upright=True)
  np.testing.assert_allclose(transform[:3, :3], np.eye(3), atol=1e-6)  # the file's frame
  data = video.get_config("tiny").data
  obs, truth = observe_tower(tool.parts, tool.materials, tool.densities, 0, data)
  valid = np.asarray(truth.valid)
  assert valid.sum() == 2 and np.asarray(truth.density)[valid].tolist() == [500.0, 9000.0]
  z = np.asarray(truth.pos)[valid, 2]
  assert z[0] < z[1]  # bottom to top: pine, then copper on it
  file_span = np.ptp(trimesh.load(path, force="mesh").vertices, 0)
  span = np.ptp(np.concatenate([p.vertices for p in tool.parts]), 0)
  np.testing.assert_allclose(span, file_span / file_span.max(), atol=1e-6)  # 1 m, upright
  size = int(data.image_size)
  assert obs["voxels"].shape == (32, 32, 32) and obs["voxels"].any()
  assert obs["image"].shape == (size, size, 3) and obs["depth"].shape == (size, size)
  _, turned = load_object(path, part_materials=materials)  # the tools' frame: turned
  assert np.abs(turned[:3, :3] / np.linalg.norm(turned[:3, 0]) - np.eye(3)).max() > 0.5


@pytest.mark.slow  # the video model decomposes on a CPU (~80 s): `make test-all`
def test_the_worked_example_decomposes_to_its_blocks(tmp_path):
  """docs/video.md's last step: `decompose --mesh tower.glb --trajectory` with the shipped
  video model reads the example's blocks upright and their densities (pine, copper)."""
  from ppdjax import decompose  # pylint: disable=import-outside-toplevel
  with open(os.path.join(VIDEO_EXAMPLE, "truth.json")) as f:
    truth = json.load(f)
  traj = tmp_path / "traj.npz"
  subprocess.run([sys.executable, "-m", "ppdjax.track", f"--video={VIDEO_EXAMPLE}/clip.mp4",
                  f"--camera={VIDEO_EXAMPLE}/camera.json",
                  f"--stickers={VIDEO_EXAMPLE}/stickers.json",
                  f"--exposure={truth['exposure']}", f"--out={traj}"],
                 cwd=ROOT, check=True, capture_output=True, timeout=300,
                 env={**os.environ, "JAX_PLATFORMS": "cpu"})
  record = decompose.run(os.path.join(VIDEO_EXAMPLE, "tower.glb"),
                         dict(zip(truth["blocks"], truth["materials"])), None,
                         os.path.join(ROOT, "assets", "video_model"), str(tmp_path / "out"),
                         trajectory=str(traj))
  assert record["protocol"] == "towers"
  assert [round(b["density"], -2) for b in record["boxes"]] == truth["densities"]
  assert record["trajectory_distance_m"] < 0.01
