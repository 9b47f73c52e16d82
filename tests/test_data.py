"""Dataset generation, storage and loading on a small config."""

import json
import os

import numpy as np
import pytest

import ppdjax  # noqa: F401
from ppdjax.configs import tiny
from ppdjax.dataset import batching, generation, storage


def small_config(**overrides):
  config = tiny.get_config()
  # two shards of the tiny preset's shape, so the tiny dataset's compiled programs serve
  config.data.num_towers = 8
  for k, v in overrides.items():
    config.data[k] = v
  return config


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
  out = str(tmp_path_factory.mktemp("ds") / "a")
  generation.generate(small_config(), out, progress=False)
  return out


def _files(path):
  out = {}
  for root, _, names in os.walk(path):
    for n in names:
      if n.endswith(".npy") or n in ("manifest.json", "DONE", "config.json"):
        with open(os.path.join(root, n), "rb") as f:
          out[os.path.relpath(os.path.join(root, n), path)] = f.read()
  return out


def test_samples_have_the_design_keys_and_shapes(dataset_dir):
  ds = storage.open_dataset(dataset_dir)
  assert len(ds) == 8 * 8
  s = ds[3]
  assert s["voxels"].shape == (32, 32, 32) and s["voxels"].dtype == np.uint8
  assert s["image"].shape == (64, 64, 3) and s["image"].dtype == np.uint8
  assert s["depth"].shape == (64, 64) and s["depth"].dtype == np.float32
  assert s["trajectories"].shape == (4, 256, 7) and s["trajectories"].dtype == np.float32
  assert s["primitives"].density.shape == (5,) and s["materials"].shape == (5,)
  s["primitives"].validate()
  assert isinstance(s["tower_id"], int)
  manifest = json.load(open(os.path.join(dataset_dir, "manifest.json")))
  assert manifest["engine"]["backend"] == "mujoco" and manifest["samples"] == 64
  for name in ("card.md", "contact_sheet.png", "density_histogram.png"):
    assert os.path.getsize(os.path.join(dataset_dir, name)) > 100


def test_splits_are_disjoint_by_tower(dataset_dir):
  towers = {}
  for split in storage.SPLITS:
    try:
      ds = storage.open_dataset(dataset_dir, split)
    except storage.DatasetError:
      continue  # 8 towers may leave a split empty
    towers[split] = {ds[i]["tower_id"] for i in range(len(ds))}
  ids = [t for v in towers.values() for t in v]
  assert len(ids) == len(set(ids)) == 8
  split = storage.split_of(np.arange(10000))
  assert abs((split == 0).mean() - 0.8) < 0.02 and abs((split == 2).mean() - 0.1) < 0.02


def test_resume_is_byte_identical(dataset_dir, tmp_path, monkeypatch):
  out = str(tmp_path / "b")
  real = storage.write_shard
  calls = []

  def interrupted(*args):
    if len(calls) == 1:
      raise KeyboardInterrupt  # killed while working on the second shard
    calls.append(1)
    return real(*args)

  monkeypatch.setattr(storage, "write_shard", interrupted)
  with pytest.raises(KeyboardInterrupt):
    generation.generate(small_config(), out, progress=False)
  assert not os.path.exists(os.path.join(out, "manifest.json"))
  monkeypatch.setattr(storage, "write_shard", real)
  generation.generate(small_config(), out, progress=False)
  assert _files(out) == _files(dataset_dir)


def test_refuses_another_config_and_bad_values(dataset_dir):
  with pytest.raises(ValueError, match="another config"):
    generation.generate(small_config(image_size=48), dataset_dir, progress=False)
  with pytest.raises(ValueError, match="config.data.image_size"):
    generation.check_config(small_config(image_size=4).data)
  with pytest.raises(ValueError, match="config.data.backend"):
    generation.check_config(small_config(backend="bullet").data)


def test_disk_full_is_reported_before_starting(tmp_path, monkeypatch):
  import shutil
  monkeypatch.setattr(shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(1, 1, 10))
  with pytest.raises(OSError, match="not enough disk space"):
    generation.generate(small_config(), str(tmp_path / "full"), progress=False)


def test_missing_or_corrupt_files_are_named(dataset_dir, tmp_path):
  import shutil
  copy = str(tmp_path / "c")
  shutil.copytree(dataset_dir, copy)
  victim = os.path.join(copy, "shard-00001", "trajectories.npy")
  with open(victim, "r+b") as f:
    f.seek(200)
    f.write(b"\x00\x01\x02")
  with pytest.raises(storage.DatasetError, match="shard-00001/trajectories.npy"):
    storage.open_dataset(copy, verify=True)
  with open(victim, "r+b") as f:
    f.truncate(100)
  with pytest.raises(storage.DatasetError, match="shard-00001/trajectories.npy"):
    storage.open_dataset(copy)
  os.remove(victim)
  with pytest.raises(storage.DatasetError, match="missing shard file .*trajectories.npy"):
    storage.open_dataset(copy)
  os.remove(os.path.join(copy, "manifest.json"))
  with pytest.raises(storage.DatasetError, match="manifest.json is missing"):
    storage.open_dataset(copy)
  with pytest.raises(storage.DatasetError, match="no dataset directory"):
    storage.open_dataset(str(tmp_path / "nowhere"))


def test_optional_fields_travel_with_the_samples_and_are_checked(dataset_dir, tmp_path):
  """A dataset whose shards all hold the optional fields (each object's push magnitudes,
  each box's thickness) gives them with its samples; a corrupt one is named, an unknown
  field refused."""
  import shutil
  copy = str(tmp_path / "o")
  shutil.copytree(dataset_dir, copy)
  with open(os.path.join(copy, "manifest.json")) as f:
    manifest = json.load(f)
  for shard in manifest["shards"]:
    folder = os.path.join(copy, shard["name"])
    arrays = {n: np.load(os.path.join(folder, f"{n}.npy")) for n in storage.FIELDS}
    rows, slots = arrays["density"].shape
    arrays["push_magnitudes"] = np.outer(1 + np.arange(rows), np.full(4, 2e3)).astype(np.float32)
    arrays["thickness"] = np.full((rows, slots), 0.01, np.float32)
    shutil.rmtree(folder)
    shard["files"] = storage.write_shard(folder, arrays)
  with open(os.path.join(copy, "manifest.json"), "w") as f:
    json.dump(manifest, f)
  ds = storage.open_dataset(copy)
  assert ds.sample_keys[-2:] == ("push_magnitudes", "thickness")
  np.testing.assert_allclose(ds[1]["push_magnitudes"], 4e3)
  assert ds.take([0, 1], keys=("thickness",))["thickness"].shape == (2, slots)
  assert "push_magnitudes" not in storage.open_dataset(dataset_dir).sample_keys
  with pytest.raises(ValueError, match="unknown fields.*speed"):
    storage.write_shard(str(tmp_path / "x"), {**arrays, "speed": arrays["thickness"]})
  with open(os.path.join(copy, manifest["shards"][0]["name"], "thickness.npy"), "r+b") as f:
    f.seek(150)
    f.write(b"\x07\x07\x07")
  with pytest.raises(storage.DatasetError, match="thickness.npy: checksum"):
    storage.open_dataset(copy, verify=True)


def test_flipped_voxel_bytes_are_caught_when_a_shard_is_first_read(dataset_dir, tmp_path):
  """Training opens datasets without verify=True: the first read of a shard checks it."""
  import shutil
  copy = str(tmp_path / "flipped")
  shutil.copytree(dataset_dir, copy)
  victim = os.path.join(copy, "shard-00000", "voxels.npy")
  with open(victim, "r+b") as f:
    f.seek(-100, os.SEEK_END)
    f.write(b"\xff")
  ds = storage.open_dataset(copy)  # opening reads headers and row counts only
  with pytest.raises(storage.DatasetError, match="shard-00000/voxels.npy: checksum"):
    ds.take([0, len(ds) - 1])
  # a manifest that agrees with the damaged file: the value range still catches it
  manifest_path = os.path.join(copy, "manifest.json")
  manifest = json.load(open(manifest_path))
  manifest["shards"][0]["files"]["voxels.npy"] = storage.sha256(victim)
  with open(manifest_path, "w") as f:
    json.dump(manifest, f)
  with pytest.raises(storage.DatasetError, match="voxels.npy: occupancy values up to 255"):
    storage.open_dataset(copy).take([0])
  assert storage.open_dataset(copy, check=False).take([0])["voxels"].max() <= 255  # opted out


def test_loader_is_deterministic_and_streams(dataset_dir):
  ds = storage.open_dataset(dataset_dir)
  a = list(batching.batches(ds, 8, seed=3))
  b = list(batching.batches(ds, 8, seed=3))
  c = list(batching.batches(ds, 8, seed=3, epoch=1))
  assert len(a) == 8 and a[0]["image"].shape == (8, 64, 64, 3)
  assert a[0]["primitives"].density.shape == (8, 5)
  assert all(np.array_equal(x["tower_id"], y["tower_id"]) for x, y in zip(a, b))
  assert not all(np.array_equal(x["tower_id"], y["tower_id"]) for x, y in zip(a, c))
  resumed = list(batching.batches(ds, 8, seed=3, start=2))
  assert np.array_equal(resumed[0]["tower_id"], a[2]["tower_id"])
  seen = np.concatenate([x["tower_id"] for x in a])
  assert len(seen) == len(ds)
  with pytest.raises(ValueError, match="batch_size"):
    next(batching.batches(ds, 0, seed=0))
  # a batch equals its samples read one by one; a slice per process, and chosen keys only
  rows = np.random.default_rng([3, 0]).permutation(len(ds))[:8]
  for i, r in enumerate(rows):
    s = ds[int(r)]
    assert np.array_equal(a[0]["image"][i], s["image"])
    assert np.array_equal(a[0]["primitives"].quat[i], s["primitives"].quat)
  half = next(batching.batches(ds, 8, seed=3, part=(1, 2), keys=("trajectories",)))
  assert set(half) == {"trajectories"}
  assert np.array_equal(half["trajectories"], a[0]["trajectories"][4:])


def test_tiny_preset_generates(tiny_dataset):
  """The tiny preset itself, as the README runs it: 16 towers x 8 configurations."""
  with open(os.path.join(tiny_dataset, "manifest.json")) as f:
    manifest = json.load(f)
  assert manifest["samples"] == 128 and manifest["towers"] == 16
  assert sum(manifest["splits"].values()) == 128
  ds = storage.open_dataset(tiny_dataset, verify=True)
  assert ds[127]["image"].shape == (64, 64, 3)
  assert ds[127]["trajectories"].shape == (4, 256, 7)


class _BlankRenderer:
  """The towers renderer's contract without a GL context; keeps the looks it was given."""

  def __init__(self):
    self.shown = []

  def render(self, prims, material_ids, seeds):
    self.shown.append(np.asarray(material_ids))
    return np.zeros((len(material_ids), 16, 16, 3), np.uint8), None


def _pendulum_data(**changes):
  """The tiny video preset's data section, four towers, a few MuJoCo C steps (both look-alike
  tests share these shapes, so their compiled programs)."""
  from ppdjax.configs import video  # pylint: disable=import-outside-toplevel
  cfg = video.get_config("tiny").data
  cfg.update(num_towers=4, towers_per_shard=4, steps=4, backend="mujoco", image_size=16,
             **changes)
  return cfg


def test_look_alike_towers_show_one_texture_for_materials_that_differ(monkeypatch):
  """`data.look`: the renderer receives what each block shows, the labels keep its material;
  "painted" shows one paint on every block, "alike_metals" steel as aluminium; a bad look is
  named."""
  from ppdjax.dataset import materials  # pylint: disable=import-outside-toplevel

  ids = np.asarray([[5, 6, 7, 8], [7, 7, -1, -1]])  # pine, aluminium, steel, copper
  assert (materials.look_ids(ids, "material") == ids).all()
  paint = materials.LOOK_NAMES.index("paint")
  assert (materials.look_ids(ids, "painted") == np.where(ids >= 0, paint, -1)).all()
  assert materials.look_ids(ids, "alike_metals").tolist() == [[5, 6, 6, 8], [6, 6, -1, -1]]
  with pytest.raises(ValueError, match="data.look"):
    materials.look_ids(ids, "shiny")
  a, b = materials.texture("paint", 1), materials.texture("paint", 2)
  assert np.abs(a.mean((0, 1)) - b.mean((0, 1))).max() < 3  # one colour, another grain
  assert (materials.texture("steel", 3) == materials.texture("steel", 3)).all()

  cfg = _pendulum_data(look="painted")
  generation.check_config(cfg)
  renderer = _BlankRenderer()
  out = generation.generate_shard(cfg, 0, 0, renderer)
  valid = out["valid"]
  assert (renderer.shown[0][valid] == paint).all() and "inertia_scale" not in out  # solid
  assert (out["materials"][valid] >= len(materials.MATERIAL_NAMES)).all()  # labels: real ones
  cfg.look = "glossy"
  with pytest.raises(ValueError, match="config.data.look"):
    generation.check_config(cfg)


def test_hollow_blocks_keep_their_material_and_carry_their_inertia():
  """`data.hollow`: blocks become shells around cores; the label is the mean density, the
  material the shell's, and the dataset keeps each block's inertia scale for the simulator."""
  from ppdjax.dataset import hollow, materials  # pylint: disable=import-outside-toplevel

  cfg = _pendulum_data(hollow=1.0)
  generation.check_config(cfg)
  out = generation.generate_shard(cfg, 0, 0, _BlankRenderer())
  valid = out["valid"]
  assert out["inertia_scale"].shape == valid.shape
  scale = out["inertia_scale"][valid]
  assert (np.abs(scale - 1) > 1e-3).mean() > 0.5  # a core of another density, or none
  real = np.asarray([materials.REAL_MATERIALS[materials.ALL_MATERIAL_NAMES[m]] * 100.0
                     for m in out["materials"][valid]])
  empty = scale > 1  # lighter cores: the block weighs less than its shell's material
  assert (out["density"][valid][empty] < real[empty]).all()
  assert np.isclose(hollow.inertia_scale(7900.0, 0.0, 0.0), 1.0)
  cfg.hollow = 1.5
  with pytest.raises(ValueError, match="config.data.hollow"):
    generation.check_config(cfg)


def test_the_lookalike_video_preset_paints_and_hollows_its_blocks():
  from ppdjax.configs import schema, video  # pylint: disable=import-outside-toplevel
  for size in ("lookalike", "lookalike_tiny"):
    config = video.get_config(size)
    schema.read(config)
    generation.check_config(config.data)
    assert (config.data.look, config.data.hollow, config.data.kind) == ("painted", 0.5,
                                                                      "pendulum")
  assert video.get_config("lookalike").train.init_from == "assets/video_model"
  assert video.get_config("paper").data.look == "material"
  # stickers on every face, a wider view in more pixels
  test = video.get_config("paper").test
  assert (test.stickers, test.fovy, tuple(test.frame)) == ("all", 42.0, (960, 1280))
  with pytest.raises(ValueError, match="lookalike"):
    video.get_config("huge")
