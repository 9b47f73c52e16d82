"""The shipped models (block towers, tools) and example tower (assets/) load and decompose."""

import importlib
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import ppdjax
from ppdjax.dataset.storage import DatasetError
from ppdjax.infer import example as decompose_example
from ppdjax.box_overlap import box_iou

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

MODEL = os.path.join(ROOT, "assets", "blocks_model")
TOOLS_MODEL = os.path.join(ROOT, "assets", "tools_model")
TOOLS_PAPER_MODEL = os.path.join(ROOT, "assets", "tools_paper_model")
VIDEO_MODEL = os.path.join(ROOT, "assets", "video_model")
LOOKALIKE_MODEL = os.path.join(ROOT, "assets", "video_lookalike_model")
EXAMPLE = os.path.join(ROOT, "assets", "blocks_example.npz")


@pytest.mark.parametrize("model_dir", [MODEL, TOOLS_MODEL, VIDEO_MODEL, LOOKALIKE_MODEL])
def test_shipped_files_are_within_the_size_limits(model_dir):
  sizes = [os.path.getsize(os.path.join(model_dir, f)) for f in os.listdir(model_dir)]
  assert max(sizes) <= 16 * 2 ** 20 and sum(sizes) <= 50 * 2 ** 20


@pytest.mark.parametrize("model,look", [(VIDEO_MODEL, "material"), (LOOKALIKE_MODEL, "painted")])
def test_shipped_video_models_read_one_strike(model, look):
  """Both video models read the pendulum's one strike; the look-alike one was fine-tuned on
  painted towers, half their blocks hollow (configs/video.py:lookalike)."""
  from ppdjax.dataset.generation import pushes_of  # pylint: disable=import-outside-toplevel
  _, config = ppdjax.load(model)
  assert config.data.kind == "pendulum" and config.model.num_pushes == 1
  assert pushes_of(config.data).is_strike
  assert config.data.get("look", "material") == look
  assert config.data.get("hollow", 0.0) == (0.5 if look == "painted" else 0.0)


@pytest.mark.slow
def test_shipped_video_model_names_the_blocks_materials():
  """Fresh 2-block towers of the real materials, struck once (MuJoCo C), seen by the
  dataset's camera: the video model's arg-max densities give most blocks' materials."""
  from ppdjax.dataset import materials, render, towers  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset.generation import pushes_of  # pylint: disable=import-outside-toplevel
  model, config = ppdjax.load(VIDEO_MODEL)
  rng = np.random.default_rng(123)
  made = [towers.sample_tower(rng, 2, material_set="real") for _ in range(4)]
  prims = ppdjax.primitives.stack([p for p, _ in made])
  ids = np.array([[materials.ALL_MATERIAL_NAMES.index(n) for n in names] + [0] * 3
                  for _, names in made])
  with render.BatchRenderer(224, 224, depth=False) as renderer:
    images, _ = renderer.render(prims, ids, np.zeros_like(ids))
  traj = ppdjax.simulate(prims, pushes_of(config.data), backend="mujoco")
  obs = {"voxels": jnp.asarray(ppdjax.voxelize(prims)), "image": jnp.asarray(images),
         "trajectories": jnp.asarray(traj, jnp.float32)}
  pred, raw = nnx.jit(lambda m, o: m.decode(o))(model, obs)
  assert np.all(np.asarray(pred.valid).sum(-1) == 2)
  slots = np.asarray(raw.density_logits)[:, :2, :100].argmax(-1)  # bottom, top
  order = np.argsort(np.asarray(prims.pos)[:, :2, 2], -1)
  true = np.take_along_axis(np.rint(np.asarray(prims.density)[:, :2] / 100) - 1, order, -1)
  assert (np.abs(slots - true) <= 2).mean() >= 0.75


@pytest.mark.slow  # about 10 s on 2 cores; `make test-all` (the fast suite stays under 10 minutes)
def test_shipped_tools_model_finds_the_parts_of_test_tools():
  """Two test tools of the tools dataset (seed 0; a knife and a hammer, 2 boxes each),
  observed as the model's own dataset was made (its labels and pushes): the tools model
  gives the right box count and meets the largest part (shape F1 on the whole test split
  is 87.4, experiments/results/tools_realistic.md)."""
  from ppdjax import primitives  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import tool_generation  # pylint: disable=import-outside-toplevel
  model, config = ppdjax.load(TOOLS_MODEL)
  assert config.name == "tools" and config.data.kind == "tools"
  decode = nnx.jit(lambda m, o: m.decode(o))
  for index in (21, 42):
    s = tool_generation.tool_sample(0, index, 224, 256, force=config.data.tool_push_force,
                                    materials=config.data.tool_materials,
                                    push=config.data.tool_push)
    prims, _ = decode(model, {k: jnp.asarray(s[k])[None]
                              for k in ("voxels", "image", "trajectories")})
    true = primitives.Primitives(**{f: jnp.asarray(s[f])[None] for f in primitives.FIELDS})
    assert int(prims.valid.sum()) == int(true.valid.sum()) == 2
    largest = int(np.argmax(np.prod(s["half_size"], -1) * s["valid"]))
    assert np.asarray(box_iou(prims, true))[0, :, largest].max() > 0.3


def test_shipped_model_recovers_the_example_tower():
  model, config = ppdjax.load(MODEL)
  assert config.name == "paper" and config.model.resnet_width == 64
  obs, true = decompose_example.load_example(EXAMPLE)
  assert obs["image"].shape == (224, 224, 3) and int(true.valid.sum()) == 4
  batch = {k: jnp.asarray(v)[None] for k, v in obs.items()}
  prims, _ = nnx.jit(lambda m, o: m.decode(o))(model, batch)
  assert int(prims.valid.sum()) == 4
  # Both are ordered bottom to top: the k-th decoded box overlaps the k-th true box (the
  # shipped model's shape F1 is 99.6 on the test split, experiments/results/blocks.md);
  # the fit (fit_boxes) takes them further.
  true_b = jax.tree.map(lambda x: jnp.asarray(x)[None], true)
  iou = np.diagonal(np.asarray(box_iou(prims, true_b))[0][:4, :4])
  assert np.all(iou > 0.5), iou
  np.testing.assert_allclose(prims.pos[0, :4], true.pos[:4], atol=0.05)


@pytest.mark.slow  # about 15 s on 2 cores; `make test-all`
def test_shipped_paper_protocol_tools_model_finds_the_boxes_of_fresh_tools():
  """Two tools of a seed no dataset used, made under the paper's protocol (their boxes
  simulated by MuJoCo C): the paper-protocol tools model gives the box count and meets
  every box, most at IoU > 0.5 (shape F1 83.5 on its test split,
  experiments/results/tools_paper.md)."""
  from ppdjax import primitives, simulate  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import tool_paper  # pylint: disable=import-outside-toplevel
  model, config = ppdjax.load(TOOLS_PAPER_MODEL)
  assert config.data.tool_protocol == "paper"
  decode = nnx.jit(lambda m, o: m.decode(o))
  pushes = ppdjax.default_pushes(config.data.tool_push_force)
  for index in (0, 1):
    s = tool_paper.tool_samples(11, index, 224, 1)[0]
    true = primitives.Primitives(**{f: jnp.asarray(s[f])[None] for f in primitives.FIELDS})
    traj = np.asarray(simulate(true, pushes, backend="mujoco"), np.float32)
    prims, _ = decode(model, {"voxels": jnp.asarray(s["voxels"])[None],
                              "image": jnp.asarray(s["image"])[None],
                              "trajectories": jnp.asarray(traj)})
    count = int(true.valid.sum())
    assert int(prims.valid.sum()) == count
    iou = np.asarray(box_iou(prims, true))[0][:count, :count]
    assert np.all(iou.max(0) > 0.3) and iou.max(0).mean() > 0.5, iou


@pytest.mark.parametrize("model,preset", [(MODEL, "paper"), (TOOLS_MODEL, "tools"),
                                          (TOOLS_PAPER_MODEL, "tools_paper"),
                                          (LOOKALIKE_MODEL, "video:lookalike")])
def test_shipped_model_evaluates_with_the_presets_rules(model, preset):
  """A shipped model's saved evaluation settings are its preset's (what
  experiments/results/blocks.md, tools.md and video_lookalike.md measured: for the blocks
  and tools models the defaults of `python -m ppdjax.evaluate --workdir=assets/...` and
  the selection horizon the example and `python -m ppdjax.decompose` pass; for the
  look-alike model what `make_decompose_fn` runs): no stale default."""
  preset, _, size = preset.partition(":")
  presets = importlib.import_module(f"ppdjax.configs.{preset}")
  _, config = ppdjax.load(model)
  expect = presets.get_config(size) if size else presets.get_config()
  assert config.eval.to_dict() == expect.eval.to_dict()


@pytest.mark.slow
def test_physics_sampling_finds_the_heavy_blocks(tmp_path):
  """Blocks 2 and 4 of the example are metal (9,800 and 9,700 kg/m³), 1 and 3 light; 64
  density samples on the fitted boxes, scored by simulation, find which two are heavy."""
  r = decompose_example.decompose_example(MODEL, EXAMPLE, str(tmp_path / "d.png"), samples=64)
  assert set(np.argsort(r["densities"])[-2:]) == {1, 3}, r["densities"]
  assert os.path.getsize(tmp_path / "d.png") > 0


def test_a_broken_example_file_is_named(tmp_path):
  bad = tmp_path / "bad.npz"
  bad.write_bytes(b"not a zip")
  with pytest.raises(DatasetError, match="not a readable example"):
    decompose_example.load_example(str(bad))
  np.savez(tmp_path / "partial.npz", voxels=np.zeros((32, 32, 32), np.uint8))
  with pytest.raises(DatasetError, match="not a readable example"):
    decompose_example.load_example(str(tmp_path / "partial.npz"))


def test_the_example_keeps_its_depth_and_camera(tmp_path):
  """The shipped example carries the dataset's depth and camera (the depth fit uses
  them); an example saved without a camera has neither."""
  from ppdjax.dataset import camera as camera_lib
  obs, true = decompose_example.load_example(EXAMPLE)
  cam = decompose_example.load_camera(EXAMPLE)
  assert obs["depth"].shape == (cam["height"], cam["width"]) == (224, 224)
  np.testing.assert_allclose(cam["intrinsics"], camera_lib.intrinsics(224, 224))
  np.testing.assert_allclose(cam["camera_from_world"], camera_lib.camera_from_world())
  sample = {**obs, "primitives": true}
  decompose_example.save_example(sample, str(tmp_path / "plain.npz"))
  assert decompose_example.load_camera(str(tmp_path / "plain.npz")) is None
  assert "depth" not in decompose_example.load_example(str(tmp_path / "plain.npz"))[0]
  # the camera's light goes with it (the image fit's shadows), and so does "no light"
  for light in ((0.3, -0.2, -0.9), None):
    path = str(tmp_path / f"lit_{light is None}.npz")
    decompose_example.save_example({**sample, "depth": obs["depth"]}, path,
                                   camera=dict(cam, light_dir=light))
    got = decompose_example.load_camera(path)["light_dir"]
    assert got is None if light is None else np.allclose(got, light)


ESTIMATOR = os.path.join(ROOT, "assets", "density_estimator")


@pytest.mark.slow  # ~23 s on 2 cores (the optional estimator): `make test-all`
def test_shipped_estimator_loads_and_reads_the_example():
  """The shipped density estimator (experiments/results/estimator.md) is within the size
  limits, loads (sha256 checked) and scores the example's true boxes from its motion."""
  from ppdjax.training import estimator
  assert os.path.getsize(os.path.join(ESTIMATOR, estimator.WEIGHTS)) <= 16 * 2 ** 20
  model, e = estimator.load(ESTIMATOR)
  obs, true = decompose_example.load_example(EXAMPLE)
  prims = jax.tree.map(lambda x: jnp.asarray(x)[None], true)
  logits = np.asarray(model(prims, jnp.asarray(obs["trajectories"], jnp.float32)[None]))[0]
  assert logits.shape == (5, 100) and np.all(np.isfinite(logits))
  assert np.all(logits[~np.asarray(true.valid)] == 0)


@pytest.mark.parametrize("model", [MODEL, TOOLS_MODEL, TOOLS_PAPER_MODEL, VIDEO_MODEL,
                                   LOOKALIKE_MODEL])
def test_shipped_decompose_settings_are_the_saved_eval_sections(model):
  """decompose.json shows the settings `make_decompose_fn(model)` runs (its saved eval
  section, the one source) and the camera of its training data."""
  from ppdjax.dataset.camera import camera_dict, check_camera
  from ppdjax.infer.decompose import model_camera, model_settings
  from ppdjax.training import checkpoints
  saved = checkpoints.read_decompose(model)
  assert saved["config"] == model_settings(model)
  size = ppdjax.load(model)[1].data.image_size
  camera = check_camera(model_camera(model))
  expect = check_camera(camera_dict(size, size))
  assert camera["height"] == camera["width"] == size
  np.testing.assert_allclose(camera["intrinsics"], expect["intrinsics"])
