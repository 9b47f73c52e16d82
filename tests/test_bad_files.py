"""Bad files and arguments at the public surfaces are refused with an error naming the file
(or argument) and the problem: dataset storage, `ppdjax.load`, the trajectory and example
readers, and the track / decompose entry points. Every file is made here, small: no
dataset is generated and no network is run (the models are abstract, `nnx.eval_shape`)."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ppdjax  # noqa: F401  pylint: disable=unused-import  (the package first: it sets up JAX as every test has it)
from ppdjax.configs import tiny
from ppdjax.conventions import TIMESTEP
from ppdjax.dataset import batching, storage
from ppdjax.infer import example
from ppdjax.primitives import Primitives
from ppdjax.training import checkpoints
from ppdjax.video import files
from conftest import cli_module

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPLIT = np.array([0, 0, 0, 0, 1, 2], np.uint8)  # 4 train, 1 val, 1 test


def _boxes(*lead):
  """Valid Primitives (lead..., 5): one box of 0.2 m, four padded slots."""
  z = lambda *s: np.zeros(lead + (5,) + s, np.float32)
  quat, valid = z(4), np.zeros(lead + (5,), bool)
  quat[..., 0], valid[..., 0] = 1, True
  return Primitives(z(3) + 0.1, z(3), quat, z() + 500, valid)


def fake_dataset(path, n=len(SPLIT)):
  """A one-shard dataset in storage's own layout, with tiny arrays (storage does not
  care about the observations' sizes); returns the manifest's path."""
  p = _boxes(n)
  arrays = {"voxels": np.zeros((n, 4, 4, 4), np.uint8), "image": np.zeros((n, 2, 2, 3), np.uint8),
            "trajectories": np.zeros((n, 1, 3, 7), np.float32),
            "depth": np.zeros((n, 2, 2), np.float32), "materials": np.zeros((n, 5), np.int32),
            "tower_id": np.arange(n), "split": SPLIT[:n],
            **{f: getattr(p, f) for f in ("half_size", "pos", "quat", "density", "valid")}}
  sums = storage.write_shard(os.path.join(path, "shard-00000"), arrays)
  manifest = {"format_version": storage.FORMAT_VERSION, "config": {"data": {"image_size": 2}},
              "shards": [{"name": "shard-00000", "samples": n, "files": sums}]}
  with open(os.path.join(path, "manifest.json"), "w") as f:
    json.dump(manifest, f)
  return os.path.join(path, "manifest.json")


def trajectory_file(path, **change):
  traj = np.zeros((300, 7))
  traj[:, 2], traj[:, 3] = 0.2, 1.0
  data = {"trajectory": traj, "dt": TIMESTEP, "initial_pose": traj[0], **change}
  np.savez(path, **data)  # as `python -m ppdjax.track` writes it (uncompressed)
  return path


def example_file(path):
  rng = np.random.default_rng(0)
  sample = {"voxels": np.zeros((32, 32, 32), np.uint8), "primitives": _boxes(),
            "image": rng.integers(0, 255, (8, 8, 3), dtype=np.uint8),
            "trajectories": rng.normal(size=(4, 64, 7)).astype(np.float32)}
  example.save_example(sample, path)  # compressed
  return path


# ---- .npz files: each reader names the file and the damage -------------------------------

def _truncate(path):
  with open(path, "r+b") as f:
    f.truncate(os.path.getsize(path) // 2)


def _flip(path):
  with open(path, "r+b") as f:  # one bit in the middle: inside an array's bytes
    f.seek(os.path.getsize(path) // 2)
    byte = f.read(1)[0]
    f.seek(-1, os.SEEK_CUR)
    f.write(bytes([byte ^ 0x10]))


def _npy(path):
  with open(path, "wb") as f:  # an .npy under the .npz name (np.save of the trajectory)
    np.save(f, np.zeros((300, 7)))


DAMAGE = [
    ("truncated", _truncate, "the archive is truncated or corrupt"),
    ("bit-flipped", _flip, "the archive is truncated or corrupt"),
    ("npy for npz", _npy, r"it is an \.npy file \(one array\); expected an \.npz"),
    ("empty", lambda p: Path(p).write_bytes(b""), "the file is empty"),
    ("text", lambda p: Path(p).write_text("trajectory,dt\n"), r"not an \.npz \(zip\) archive"),
]
READERS = [
    ("trajectory", trajectory_file, files.read_trajectory, files.VideoFileError),
    ("example", example_file, example.load_example, storage.DatasetError),
    ("example camera", example_file, example.load_camera, storage.DatasetError),
]


@pytest.mark.parametrize("reader", READERS, ids=[r[0] for r in READERS])
@pytest.mark.parametrize("damage", DAMAGE, ids=[d[0] for d in DAMAGE])
def test_damaged_npz_files_are_named(tmp_path, reader, damage):
  _, make, read, error = reader
  _, spoil, message = damage
  path = make(str(tmp_path / "f.npz"))
  read(path)  # intact, it reads
  spoil(path)
  with pytest.raises(error, match=f"{re.escape(path)}: not a readable .* file: {message}"):
    read(path)


@pytest.mark.parametrize("key, value, message", [
    ("voxels", np.zeros((16, 16, 16), np.uint8), r"voxels has shape \(16, 16, 16\)"),
    ("image", np.zeros((8, 8, 3), np.float32), "expected a uint8 image"),
    ("trajectories", np.full((4, 64, 7), np.nan, np.float32), "trajectories or depth contain NaN"),
    ("true_quat", np.zeros((5, 4), np.float32), "its true boxes: Primitives.quat: not unit norm"),
])
def test_example_contents_are_named(tmp_path, key, value, message):
  path = example_file(str(tmp_path / "e.npz"))
  arrays = dict(np.load(path))
  np.savez(path, **{**arrays, key: value})
  with pytest.raises(storage.DatasetError, match=f"{re.escape(path)} is not a readable "
                                                 f"example tower: {message}"):
    example.load_example(path)


@pytest.mark.parametrize("read", [files.read_trajectory, example.load_example, files.read_video,
                                  files.read_camera, files.read_stickers, checkpoints.load,
                                  storage.open_dataset])
def test_missing_files_are_file_not_found_errors_naming_the_path(tmp_path, read):
  path = str(tmp_path / "nowhere")
  with pytest.raises(FileNotFoundError, match=re.escape(path)) as got:
    read(path)
  assert isinstance(got.value, ValueError)  # and each surface's own error type


@pytest.mark.parametrize("name, where, value, message", [
    ("trajectory", np.s_[7, 3:7], 0.0, r"trajectory row 7 has a quaternion of norm 0 \(1 such\)"),
    ("trajectory", np.s_[10:20, 4], np.nan, "contains NaN"),
    ("initial_pose", np.s_[3:7], 0.0, "initial_pose has a quaternion of norm 0"),
    ("trajectory", np.s_[:, 3], 2.0, "row 0 has a quaternion of norm 2"),
])
def test_trajectory_poses_must_hold_unit_quaternions(tmp_path, name, where, value, message):
  arrays = {"trajectory": np.zeros((300, 7)), "initial_pose": np.array([0, 0, 0.2, 1, 0, 0, 0.])}
  arrays["trajectory"][:, 3] = 1
  arrays[name][where] = value
  path = trajectory_file(str(tmp_path / "t.npz"), **arrays)
  with pytest.raises(files.VideoFileError, match=f"{re.escape(path)}: .*{message}"):
    files.read_trajectory(path)


def test_trajectory_arrays_of_the_wrong_kind(tmp_path):
  for change, message in [({"dt": np.array([TIMESTEP, TIMESTEP])}, r"dt is an array of shape"),
                          ({"trajectory": np.zeros((0, 7))}, r"T >= 1"),
                          ({"trajectory": np.zeros((5, 7, 1))}, r"expected trajectory \(T, 7\)")]:
    path = trajectory_file(str(tmp_path / "t.npz"), **change)
    with pytest.raises(files.VideoFileError, match=message):
      files.read_trajectory(path)


@pytest.mark.parametrize("text, message", [
    ('{"intrinsics": [[1, 0, 0], [0, 1, 0]], "camera_from_world": []}',
     r"intrinsics must be \(3, 3\), got shape \(2, 3\)"),
    ('{"intrinsics": "eye", "camera_from_world": 1}', "must be an array of numbers"),
    ("", "the file is empty"),
    ("[1, 2]", "expected a JSON object"),
])
def test_camera_json_contents_are_named(tmp_path, text, message):
  (tmp_path / "cam.json").write_text(text)
  with pytest.raises(files.VideoFileError, match=message):
    files.read_camera(str(tmp_path / "cam.json"))


def test_stickers_initial_pose_needs_a_unit_quaternion(tmp_path):
  (tmp_path / "st.json").write_text(json.dumps({"stickers": np.zeros((4, 3)).tolist(),
                                                "initial_pose": [0, 0, 0.2, 0, 0, 0, 0]}))
  with pytest.raises(files.VideoFileError, match="initial_pose has a quaternion of norm 0"):
    files.read_stickers(str(tmp_path / "st.json"))


# ---- datasets: manifest, indices, batches -------------------------------------------------

def _drop(*keys):
  def change(m):
    d = m
    for k in keys[:-1]:
      d = d[k]
    del d[keys[-1]]
  return change


@pytest.mark.parametrize("change, message", [
    (_drop("shards"), r"manifest.json: missing key 'shards'"),
    (_drop("shards", 0, "files"), r"manifest.json: shards\[0\] is missing key files"),
    (_drop("shards", 0, "name"), r"manifest.json: shards\[0\] is missing key name"),
    (_drop("shards", 0, "files", "voxels.npy"), r"missing key files/voxels.npy"),
    (lambda m: m.__setitem__("shards", []), "'shards' must be a non-empty list"),
    (lambda m: m.__setitem__("format_version", 0), "format version 0"),
    ("", r"manifest.json is corrupt: the file is empty"),
    ('{"format_version": 1, ', r"manifest.json is corrupt: not valid JSON"),
    ("[1]", r"manifest.json is corrupt: expected a JSON object"),
])
def test_bad_manifests_are_named(tmp_path, change, message):
  path = fake_dataset(str(tmp_path))
  storage.open_dataset(str(tmp_path))
  if isinstance(change, str):
    text = change
  else:
    manifest = json.load(open(path))
    change(manifest)
    text = json.dumps(manifest)
  with open(path, "w") as f:
    f.write(text)
  with pytest.raises(storage.DatasetError, match=message):
    storage.open_dataset(str(tmp_path))


def test_a_manifest_without_camera_or_image_size_names_the_missing_record(tmp_path):
  path = fake_dataset(str(tmp_path))
  manifest = json.load(open(path))
  del manifest["config"]
  json.dump(manifest, open(path, "w"))
  with pytest.raises(storage.DatasetError, match="manifest.json: no usable camera record"):
    storage.open_dataset(str(tmp_path)).camera  # pylint: disable=expression-not-assigned


def test_dataset_indices_are_ints_in_range(tmp_path):
  fake_dataset(str(tmp_path))
  ds = storage.open_dataset(str(tmp_path))
  assert ds[np.int64(2)]["tower_id"] == 2 and ds[-1]["tower_id"] == 5
  for bad in (1.7, np.float32(1.0), True, "1", None):
    with pytest.raises(TypeError, match=f"index must be an int, got {re.escape(repr(bad))}"):
      ds[bad]  # pylint: disable=pointless-statement
  with pytest.raises(IndexError, match=f"sample index 6 out of range for the 6 samples of "
                                       f"{re.escape(str(tmp_path))}"):
    ds[6]  # pylint: disable=pointless-statement
  with pytest.raises(IndexError, match="sample index -7"):
    ds.take([0, -7])
  for bad in ([1.5], np.zeros((1, 1), int), 3):
    with pytest.raises(TypeError, match="1-D sequence of ints"):
      ds.take(bad)
  empty = ds.take([])
  assert empty["image"].shape == (0, 2, 2, 3) and empty["image"].dtype == np.uint8
  assert empty["primitives"].quat.shape == (0, 5, 4) and empty["tower_id"].shape == (0,)
  assert ds.take([], keys="depth")["depth"].shape == (0, 2, 2)


def test_batches_larger_than_the_split_are_refused_unless_asked_for(tmp_path):
  fake_dataset(str(tmp_path))
  train = storage.open_dataset(str(tmp_path), "train")
  with pytest.raises(ValueError, match=r"batch_size=5 is larger than the 4 samples of "
                                       r"split 'train' of .*drop_remainder=False"):
    next(batching.batches(train, 5, seed=0))
  (only,) = batching.batches(train, 5, seed=0, drop_remainder=False)
  assert sorted(only["tower_id"]) == [0, 1, 2, 3]
  assert len(list(batching.batches(train, 4, seed=0))) == 1
  for kwargs, message in [(dict(batch_size=2.0), "batch_size must be a whole number >= 1"),
                          (dict(seed=-1), "seed must be a whole number >= 0"),
                          (dict(start=-1), "start must be"), (dict(start=3), "start=3 is past"),
                          (dict(epoch=0.5), "epoch must be")]:
    args = {"batch_size": 2, "seed": 0, **kwargs}
    with pytest.raises(ValueError, match=message):
      next(batching.batches(train, args.pop("batch_size"), **args))


# ---- models: config.json, export.json, weights ---------------------------------------------

def _export_of(folder, config):
  """An export folder of `config`'s model with zero weights (from the abstract model:
  nothing is initialised or compiled)."""
  from flax import nnx  # pylint: disable=import-outside-toplevel
  _, abstract = checkpoints._abstract_model(config)  # pylint: disable=protected-access
  flat = checkpoints._flat(nnx.to_pure_dict(abstract))  # pylint: disable=protected-access
  weights = os.path.join(folder, "weights-00.npz")
  np.savez(weights, **{k: np.zeros(v.shape, v.dtype) for k, v in flat.items()})
  checkpoints.save_config(folder, config)
  record = {"dtype": "float32",
            "files": [{"name": "weights-00.npz", "sha256": storage.sha256(weights)}]}
  with open(os.path.join(folder, checkpoints.EXPORT), "w") as f:
    json.dump(record, f)
  return folder


@pytest.mark.parametrize("name, text, message", [
    ("config.json", "", "config.json is corrupt: the file is empty"),
    ("config.json", "{'model': 1}", "config.json is corrupt: not valid JSON"),
    ("config.json", '"tiny"', "config.json is corrupt: expected a JSON object"),
    ("config.json", '{"model": {"widht": 3}}', "config.json: config.model has no key widht"),
    ("export.json", "", "export.json is corrupt: the file is empty"),
    ("export.json", "{}", "export.json is corrupt: 'files' must list the weights files"),
    ("decompose.json", "nope", "decompose.json is corrupt: not valid JSON"),
])
def test_bad_model_json_files_are_named(tmp_path, name, text, message):
  checkpoints.save_config(str(tmp_path), tiny.get_config())
  (tmp_path / checkpoints.EXPORT).write_text('{"files": []}')
  (tmp_path / name).write_text(text)
  with pytest.raises(checkpoints.CheckpointError, match=message):
    checkpoints.read_decompose(str(tmp_path))
    checkpoints.load(str(tmp_path))


def test_a_config_json_of_another_model_is_refused_on_load(tmp_path):
  """The user's case: the weights of one model under the config.json of another used to
  load arrays of the wrong shape, to fail later inside opt_einsum."""
  config, wider, branched = tiny.get_config(), tiny.get_config(), tiny.get_config()
  wider.model.feature = 32
  branched.model.density_branch = True  # arrays the weights do not have at all
  folder = _export_of(str(tmp_path), config)
  checkpoints.load(folder)  # its own config: it loads
  checkpoints.save_config(folder, wider)
  with pytest.raises(checkpoints.CheckpointError,
                     match=rf"{re.escape(folder)}/config.json does not match the weights: "
                           r"array \S+ is \([\d, ]+\) in .* but \([\d, ]+\) in the model"):
    checkpoints.load(folder)
  checkpoints.save_config(folder, branched)
  with pytest.raises(checkpoints.CheckpointError, match="arrays the weights lack .*density"):
    checkpoints.load(folder)


def test_a_training_checkpoint_under_another_config_is_refused_on_load(tmp_path):
  import jax  # pylint: disable=import-outside-toplevel
  import orbax.checkpoint as ocp  # pylint: disable=import-outside-toplevel
  from flax import nnx  # pylint: disable=import-outside-toplevel
  config, other = tiny.get_config(), tiny.get_config()
  other.model.hidden = 32
  workdir = str(tmp_path / "run")
  checkpoints.save_config(workdir, config)
  _, abstract = checkpoints._abstract_model(config)  # pylint: disable=protected-access
  zeros = jax.tree.map(lambda v: np.zeros(v.shape, v.dtype), nnx.to_pure_dict(abstract))
  latest, best = checkpoints.managers(workdir, 1)
  best.save(1, args=ocp.args.Composite(model=ocp.args.StandardSave(zeros)),
            metrics={"val_loss": 1.0})
  best.wait_until_finished()
  latest.close()
  best.close()
  checkpoints.load(workdir)
  checkpoints.save_config(workdir, other)
  with pytest.raises(checkpoints.CheckpointError,
                     match=r"config.json does not match the weights: array .* in .*best/1"):
    checkpoints.load(workdir)


# ---- entry points -------------------------------------------------------------------------

def test_decompose_checks_its_files_first(tmp_path):
  decompose = cli_module("ppdjax.decompose")
  mesh = tmp_path / "m.obj"
  with pytest.raises(FileNotFoundError, match=f"{re.escape(str(mesh))}: no such mesh file"):
    decompose.check_files(str(mesh), os.path.join(ROOT, "assets", "video_model"))
  mesh.write_text("v 0 0 0\n")
  with pytest.raises(FileNotFoundError, match="no such model folder"):
    decompose.check_files(str(mesh), str(tmp_path / "model"))
  _npy(str(tmp_path / "t.npz"))
  with pytest.raises(files.VideoFileError, match=r"t.npz: not a readable .* an \.npy file"):
    decompose.check_files(str(mesh), os.path.join(ROOT, "assets", "video_model"),
                          str(tmp_path / "t.npz"))


@pytest.mark.parametrize("flag, message", [("--fps=-5", "--fps must be positive"),
                                           ("--exposure=2", "--exposure must be in [0, 1]")])
def test_track_refuses_a_bad_frame_rate_or_shutter(flag, message):
  """A subprocess: ppdjax.track's flags would clash with ppdjax.decompose's in this one."""
  run = subprocess.run([sys.executable, "-m", "ppdjax.track", "--video=v.mp4",
                        "--camera=c.json", "--stickers=s.json", flag], cwd=ROOT,
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert run.returncode != 0
  assert message in run.stderr and "got " + flag.split("=")[1] in run.stderr, run.stderr[-2000:]
