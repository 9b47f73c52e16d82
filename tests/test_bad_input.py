"""Bad and real-world input on the public surfaces: meshes as users export them, boxes,
simulation, settings and observations. Each bad input gets an error naming the problem;
nothing here compiles a large program (every check runs before one would)."""

import os
import warnings

import numpy as np
import pytest
import trimesh

import ppdjax
from ppdjax import primitives
from ppdjax.dataset import meshes
from ppdjax.dataset.camera import camera_dict, check_camera
from ppdjax.dataset.towers import sample_towers
from ppdjax.infer.config import DecomposeConfig
from ppdjax.sim import rollout_mujoco

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _textured(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
  """The mesh as a texture-mapped export holds it: every face its own vertices and UVs."""
  mesh = mesh.copy()
  mesh.unmerge_vertices()
  uv = np.random.default_rng(0).random((len(mesh.vertices), 2))
  mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
  return mesh


def _textured_obj(path, extents=(0.4, 0.4, 0.4)) -> str:
  """A cube as Blender writes an OBJ: shared positions, a texture coordinate per corner."""
  box = trimesh.creation.box(extents=extents)
  lines = [f"v {x} {y} {z}" for x, y, z in box.vertices]
  faces = []
  for i, face in enumerate(box.faces):
    lines += [f"vt {(i + c) % 7 / 7:.4f} {c / 3:.4f}" for c in range(3)]
    faces.append("f " + " ".join(f"{v + 1}/{3 * i + c + 1}" for c, v in enumerate(face)))
  path.write_text("\n".join(lines + faces) + "\n")
  return str(path)


@pytest.fixture(autouse=True)
def _no_material_warning():
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="no materials or densities given")
    yield


def test_a_textured_obj_is_one_part_and_one_box(tmp_path):
  path = _textured_obj(tmp_path / "cube.obj")
  assert len(trimesh.load(path).vertices) > 8  # split at the seams, as exported
  tool, _ = ppdjax.load_object(path)
  assert len(tool.parts) == 1
  prims, _ = ppdjax.primitives_from_mesh(trimesh.load(path))
  assert int(prims.valid.sum()) == 1


def test_a_glb_scene_of_two_textured_meshes_is_two_parts(tmp_path):
  scene = trimesh.Scene()
  for name, extents, offset in (("head", (0.4, 0.1, 0.1), (0, 0, 0)),
                                ("handle", (0.1, 0.1, 0.3), (0.25, 0, 0.1))):
    part = trimesh.creation.box(extents=extents).apply_translation(offset)
    scene.add_geometry(_textured(part), node_name=name, geom_name=name)
  scene.export(tmp_path / "tool.glb")
  tool, _ = ppdjax.load_object(str(tmp_path / "tool.glb"))
  assert tool.names == ("head", "handle")
  prims, _ = ppdjax.primitives_from_mesh(trimesh.load(tmp_path / "tool.glb"))  # a Scene
  assert int(prims.valid.sum()) == 2


@pytest.mark.parametrize("extents", [(0.4, 0.4, 0.4), (1.0, 0.1, 0.1), (0.5, 0.5, 0.1)],
                         ids=["cube", "square rod", "square plate"])
def test_symmetric_shapes_rest_on_a_face(extents):
  """Equal spreads leave PCA's axes arbitrary; the frame takes the faces' directions, so
  the box is axis-aligned: its bounding box is the box itself."""
  turn = trimesh.transformations.random_rotation_matrix(np.random.default_rng(1).random(3))
  box = trimesh.creation.box(extents=extents).apply_transform(turn)
  parts, _ = meshes.normalize(box)
  union = trimesh.util.concatenate(parts)
  np.testing.assert_allclose(np.prod(union.extents), union.volume, rtol=1e-6)
  np.testing.assert_allclose(sorted(union.extents), sorted(np.asarray(extents) /
                                                           max(extents)), atol=1e-6)


def test_hollow_and_overlapping_parts_are_refused_by_name(tmp_path):
  inner = trimesh.creation.box(extents=(0.8, 0.8, 0.8))
  inner.invert()  # a cavity: the inner shell faces inward
  trimesh.util.concatenate([trimesh.creation.box(extents=(1, 1, 1)), inner]).export(
      tmp_path / "hollow.stl")
  with pytest.raises(ValueError, match="part 'part1' .* facing inward inside part 'part0'"):
    ppdjax.load_object(str(tmp_path / "hollow.stl"))
  cross = trimesh.util.concatenate([trimesh.creation.box(extents=(1, 0.2, 0.2)),
                                    trimesh.creation.box(extents=(0.2, 1, 0.2))])
  cross.export(tmp_path / "cross.stl")
  with pytest.raises(ValueError, match="'part0' and 'part1' .* overlap"):
    ppdjax.load_object(str(tmp_path / "cross.stl"))
  with pytest.raises(ValueError, match="overlap"):
    ppdjax.primitives_from_mesh(cross)
  stacked = [trimesh.creation.box(extents=(0.4, 0.4, 0.2)),  # touching is not overlapping
             trimesh.creation.box(extents=(0.2, 0.2, 0.2)).apply_translation((0, 0, 0.2))]
  trimesh.util.concatenate(stacked).export(tmp_path / "stack.stl")
  tool, _ = ppdjax.load_object(str(tmp_path / "stack.stl"), part_materials="stone")
  mass = sum(p.volume for p in tool.parts)
  np.testing.assert_allclose(mass, sum(p.volume for p in meshes.normalize(stacked)[0]))


def test_many_parts_merge_into_boxes_or_are_refused():
  cube = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
  row = lambda n: trimesh.util.concatenate(
      [cube.copy().apply_translation((0.1 * i, 0.1 * (i % 3), 0)) for i in range(n)])
  prims, _ = ppdjax.primitives_from_mesh(row(30))  # seconds, not minutes
  assert int(prims.valid.sum()) == 5
  with pytest.raises(ValueError, match="65 parts; at most 64"):
    ppdjax.primitives_from_mesh(row(65))


def _one_box(**fields):
  prims = primitives.make(np.array([[0.1, 0.2, 0.3]]), np.zeros((1, 3)))
  return prims.replace(**{k: np.asarray(v, np.float32) for k, v in fields.items()})


@pytest.mark.parametrize("fields, message", [
    ({"half_size": [[-0.1, 0.2, 0.3]] + [[0.05] * 3] * 4}, "half_size: negative"),
    ({"quat": [[2.0, 0, 0, 0]] * 5}, "quat: not unit norm"),
    ({"density": [np.nan] + [1000.0] * 4}, "density: contains NaN"),
], ids=["negative half size", "quaternion of norm 2", "NaN density"])
def test_mass_properties_validate_concrete_boxes(fields, message):
  with pytest.raises(ValueError, match=message):
    ppdjax.mass_properties(_one_box(**fields))


def test_simulate_refuses_unstable_densities_and_names_a_diverged_rollout():
  towers = sample_towers(5, 2)
  light = towers.replace(density=np.where(towers.valid, np.float32(10.0), towers.density))
  for backend in ("mjx", "box_plane", "mujoco"):  # refused before anything compiles
    with pytest.raises(ValueError, match=r"densities must lie in \[100, 10000\]"):
      ppdjax.simulate(light, backend=backend)
  # the ends as float32 refinement reaches them (exp(log(10,000)) = 10,000.001) are in range
  ends = towers.replace(density=np.where(towers.valid, np.float32(np.exp(np.float32(
      np.log(10000.0)))), towers.density))
  assert np.asarray(ppdjax.simulate(ends, backend="mujoco")).shape[:2] == (2, 4)
  # the C engine itself, below the range: MuJoCo stops the rollout, and it is named
  with pytest.raises(rollout_mujoco.UnstableRollout, match=r"object \(\d,\) under push \d at "
                     r"step \d+"):
    rollout_mujoco.simulate(light, ppdjax.default_pushes())


@pytest.mark.parametrize("change, message", [
    ({"select.prior_weight": float("nan")}, "select.prior_weight must be finite"),
    ({"refine.prior_weight": -1.0}, "refine.prior_weight must be finite and >= 0"),
    ({"refine.steps": -1}, "refine.steps must be a whole number"),
    ({"select.samples": 2.5}, "select.samples must be a whole number"),
])
def test_decompose_settings_are_checked_when_made(change, message):
  with pytest.raises(ValueError, match=message):
    DecomposeConfig().replace(**change)


@pytest.mark.parametrize("height", [0, -5, 64.5, float("nan")])
def test_a_camera_of_no_size_is_refused(height):
  with pytest.raises(ValueError, match="height and width must be whole numbers"):
    check_camera({**camera_dict(64, 64), "height": height})


@pytest.fixture(scope="module")
def shipped():
  """The shipped model, its example observation and a decompose function (not compiled:
  every case below is refused first)."""
  from ppdjax.infer import example
  model = ppdjax.load(os.path.join(ROOT, "assets", "blocks_model"))
  obs = example.load_example(os.path.join(ROOT, "assets", "blocks_example.npz"))[0]
  return model, obs, ppdjax.make_decompose_fn(model)


def _traj(obs, f):
  return {**obs, "trajectories": f(np.array(obs["trajectories"], np.float32))}


@pytest.mark.parametrize("edit, message", [
    (lambda t: t * 1000.0, "were these millimetres"),
    (lambda t: t[:, :3], "3 steps; at least 30"),
    (lambda t: np.concatenate([t[..., :3], 0 * t[..., 3:]], -1), "quaternions .* unit norm"),
], ids=["millimetres", "three steps", "zero quaternions"])
def test_decompose_names_a_bad_trajectory_before_compiling(shipped, edit, message):
  import jax
  _, obs, decompose = shipped
  with pytest.raises(ValueError, match=message):
    decompose(_traj(obs, edit), jax.random.key(0))


def test_decompose_refuses_pushes_the_model_does_not_read(shipped):
  model = shipped[0]
  two = ppdjax.Pushes(np.float32([[1, -1, 1], [-1, -1, 1]]), np.zeros((2, 3), np.float32),
                      np.full(2, 1e5, np.float32))
  with pytest.raises(ValueError, match="pushes: 2 given; the model reads 4"):
    ppdjax.make_decompose_fn(model, pushes=two)


@pytest.mark.parametrize("call, error, message", [
    (lambda: ppdjax.sample_towers(0, 0), ValueError, "count must be an int >= 1"),
    (lambda: ppdjax.sample_towers(0, 2.5), ValueError, "count must be an int >= 1"),
    (lambda: ppdjax.sample_towers("a", 2), ValueError, "seed must be an int >= 0"),
    (lambda: ppdjax.voxelize([1, 2, 3]), TypeError, "expected ppdjax.Primitives, got list"),
    (lambda: ppdjax.voxelize(_one_box(pos=np.full((5, 3), np.nan))), ValueError,
     "pos: contains NaN"),
    (lambda: ppdjax.simulate(_one_box(), pushes=[1, 2], backend="mujoco"), TypeError,
     "pushes: expected ppdjax.Pushes"),
    (lambda: primitives.make(-0.1 * np.ones((2, 3)), np.zeros((2, 3))), ValueError,
     "half_size: negative"),
], ids=["no towers", "fractional count", "text seed", "voxelize a list", "NaN position",
        "pushes as a list", "negative box"])
def test_boxes_and_towers_are_checked_where_they_enter(call, error, message):
  with pytest.raises(error, match=message):
    call()


@pytest.mark.parametrize("option, message", [
    ({"fps": -5.0}, "fps must be finite and positive"),
    ({"push_time": 10.0}, r"push_time must be in \[0, 0.03333\)"),
    ({"dt": 0.0}, "dt must be finite and > 0"),
    ({"steps": 2.5}, "steps must be None or an int"),
    ({"gate_px": float("nan")}, "gate_px must be None or finite"),
    ({"smoothing": -1.0}, "smoothing must be finite and >= 0"),
    ({"exposure": 1.5}, r"exposure must be a fraction of the frame period in \[0, 1\]"),
])
def test_track_poses_names_a_bad_option(option, message):
  from ppdjax.video import track_poses
  frames = np.zeros((3, 8, 8, 3), np.uint8)  # 3 frames at 60 fps: 1/30 s
  args = (frames, np.diag([10.0, 10.0, 1.0]), np.eye(4), np.eye(4)[:, :3] * 0.1,
          np.float64([0, 0, 0.5, 1, 0, 0, 0]))
  with pytest.raises(ValueError, match=message):
    track_poses(*args, **{"fps": 60.0, **option})


def test_a_nan_setting_is_refused_where_the_config_is_read():
  from ppdjax.configs import schema
  config = schema.default_config()
  config.train.density_weight = float("nan")  # `< 0` alone would let it through
  with pytest.raises(schema.ConfigError, match="train.density_weight must be finite"):
    schema.read(config)
