"""Dataset storage: `.npy` shards with a manifest, random access, and a streaming loader.

Layout of a dataset directory:

  config.json            the generating config (a directory never mixes two configs)
  shard-00000/           one folder per shard: one .npy file per field, (n, ...) arrays
    voxels.npy image.npy depth.npy trajectories.npy half_size.npy pos.npy quat.npy
    density.npy valid.npy materials.npy tower_id.npy split.npy
    DONE                 written last: the files' SHA-256, so a resumed run can trust them
  manifest.json          format version, config, seed, counts, engine, per-shard checksums

Why `.npy`: numpy memory-maps them, so a sample is read without loading its shard, the
bytes are a pure function of the arrays (byte-identical reruns), and nothing beyond numpy
is needed to read a dataset.

Integrity: opening a dataset checks that every file exists and has the manifest's row
count; the first time a process reads from a shard, it checks the shard's SHA-256 sums
against the manifest and that its voxels are 0/1 (`check=False` skips this; about 33 s
once for the 31 GB paper set), so flipped bytes are named instead of trained on.
`verify=True` checks every shard's sums when the dataset is opened.

Errors: a missing file raises `MissingFileError` (a DatasetError and a FileNotFoundError),
any other problem with the files `DatasetError` (a ValueError), each naming the file;
Files are read through `readers` (errors that name the file).
"""

from __future__ import annotations

import hashlib
import json
import numbers
import os
import threading

import numpy as np

from ppdjax.conventions import OBS_KEYS, PUSH_MAGNITUDES
from ppdjax import primitives
from ppdjax.dataset import camera
from ppdjax.dataset.readers import read_json
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import RESTITUTION, Pushes, default_pushes

FORMAT_VERSION = 1
# One .npy file per field: the observations, depth, the Primitives fields, and labels.
FIELDS = OBS_KEYS + ("depth",) + primitives.FIELDS + ("materials", "tower_id", "split")
SAMPLE_KEYS = OBS_KEYS + ("depth", "primitives", "materials", "tower_id")  # what a sample holds
# Fields some datasets add, in every shard or none: push magnitudes (P,) N, parts' thinnest
# sides (K,) m, category (tools); hollow blocks' `Primitives.inertia_scale` (K,).
OPTIONAL_FIELDS = (PUSH_MAGNITUDES, "thickness", "category", "inertia_scale")
SPLITS = {"train": 0, "val": 1, "test": 2}


def pushes_from_record(p: dict) -> Pushes:
  """Pushes from a manifest's record (`generation.pushes_record` writes it)."""
  strikers = p.get("striker_masses")
  return Pushes(np.asarray(p["sources"], np.float32), np.asarray(p["targets"], np.float32),
                np.asarray(p["magnitudes"], np.float32), int(p["duration"]),
                None if strikers is None else np.asarray(strikers, np.float32),
                float(p.get("restitution", RESTITUTION))).validate()


class DatasetError(ValueError):
  """A dataset directory is missing, incomplete or corrupt (the message names the file)."""


class MissingFileError(DatasetError, FileNotFoundError):
  """A file or directory that is not there: both the surface's error and FileNotFoundError."""


def sha256(path: str) -> str:
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
      h.update(block)
  return h.hexdigest()


def split_of(tower_id: np.ndarray, fractions=(0.8, 0.1, 0.1)) -> np.ndarray:
  """Split per tower (0 train, 1 val, 2 test) from a hash of its id: never spans splits."""
  u = (np.asarray(tower_id, np.uint64) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(11)
  u = u.astype(np.float64) / float(1 << 53)
  return np.searchsorted(np.cumsum(fractions)[:-1], u, side="right").astype(np.uint8)


def write_shard(directory: str, arrays: dict[str, np.ndarray]) -> dict[str, str]:
  """Writes one shard atomically (temp folder, then rename); returns file checksums."""
  missing = set(FIELDS) - set(arrays)
  if missing:
    raise ValueError(f"shard arrays lack fields {sorted(missing)}")
  unknown = set(arrays) - set(FIELDS) - set(OPTIONAL_FIELDS)
  if unknown:
    raise ValueError(f"shard arrays hold unknown fields {sorted(unknown)}")
  tmp = directory + ".tmp"
  os.makedirs(tmp, exist_ok=True)
  sums = {}
  try:
    for name in FIELDS + tuple(f for f in OPTIONAL_FIELDS if f in arrays):
      path = os.path.join(tmp, f"{name}.npy")
      np.save(path, np.ascontiguousarray(arrays[name]))
      sums[f"{name}.npy"] = sha256(path)
    with open(os.path.join(tmp, "DONE"), "w") as f:
      json.dump(sums, f, indent=1, sort_keys=True)
  except OSError as e:
    raise OSError(e.errno, f"could not write shard {tmp} ({e.strerror}); is the disk full?")
  os.replace(tmp, directory)
  return sums


def shard_complete(directory: str) -> dict[str, str] | None:
  """The shard's checksums if it is complete and its files match them, else None."""
  done = os.path.join(directory, "DONE")
  if not os.path.exists(done):
    return None
  try:  # a DONE cut short by a crash: the shard is made again
    sums = read_json(done, error=DatasetError, missing=MissingFileError)
  except DatasetError:
    return None
  for name, digest in sums.items():
    path = os.path.join(directory, name)
    if not os.path.exists(path) or sha256(path) != digest:
      return None
  return sums


def _check_manifest(manifest: dict, where: str) -> None:
  """DatasetError naming the manifest and a key it lacks (not a bare KeyError later)."""
  if manifest.get("format_version") != FORMAT_VERSION:
    raise DatasetError(f"{where}: format version {manifest.get('format_version')} != "
                       f"{FORMAT_VERSION}")
  shards = manifest.get("shards")
  if not isinstance(shards, list) or not shards:
    raise DatasetError(f"{where}: " + ("missing key 'shards'" if shards is None else
                                       "'shards' must be a non-empty list"))
  for s, shard in enumerate(shards):
    lacks = [k for k in ("name", "samples", "files")
             if not isinstance(shard, dict) or k not in shard]
    files = {} if lacks or not isinstance(shard["files"], dict) else shard["files"]
    lacks += [f"files/{n}.npy" for n in FIELDS if not lacks and f"{n}.npy" not in files]
    if lacks:
      raise DatasetError(f"{where}: shards[{s}] is missing key {', '.join(lacks)}")


class Dataset:
  """Random access to samples of a generated dataset (memory-mapped, nothing loaded).

  `len(ds)` samples; `ds[i]` is a dict with the keys SAMPLE_KEYS: "voxels" (32,32,32)
  uint8, "image" (H,W,3) uint8, "trajectories" (P,256,7) float32, "depth" (H,W) float32,
  "primitives" Primitives (K = 5, valid mask), "materials" (5,) int (-1 padding),
  "tower_id" int.

  Indexing follows Python's sequences: `ds[i]` takes an int (or NumPy integer), negative
  counting from the end; another type raises TypeError, an index out of range IndexError,
  an unknown sample key KeyError; problems with the files raise DatasetError.

  Args:
    path: the dataset directory (written by `python -m ppdjax.generate`).
    split: "train", "val", "test" or None (all samples).
    verify: check every shard's checksums now.
    check: check a shard's checksums and voxel values when this object first reads it.
  """

  def __init__(self, path: str, split: str | None = None, verify: bool = False,
               check: bool = True):
    if not isinstance(path, (str, os.PathLike)):
      raise DatasetError(f"path must be a dataset directory, got {type(path).__name__}")
    if split is not None and split not in SPLITS:
      raise ValueError(f"split must be one of {tuple(SPLITS)} or None, got {split!r}")
    path = os.fspath(path)
    manifest_path = os.path.join(path, "manifest.json")
    if not os.path.isdir(path):
      raise (DatasetError(f"{path} is a file, not a dataset directory")
             if os.path.exists(path) else MissingFileError(f"no dataset directory at {path}"))
    if not os.path.exists(manifest_path):
      raise MissingFileError(f"{manifest_path} is missing: generation did not finish "
                             "(run `python -m ppdjax.generate` again to resume it)")
    self.manifest = read_json(manifest_path, error=DatasetError, missing=MissingFileError)
    _check_manifest(self.manifest, manifest_path)
    self.path, self.split, self._manifest_path = path, split, manifest_path
    self._checked = set() if check else set(range(len(self.manifest["shards"])))
    self._lock = threading.Lock()
    self._shards, index = [], []
    first = self.manifest["shards"][0]["files"] if self.manifest["shards"] else {}
    self.fields = FIELDS + tuple(f for f in OPTIONAL_FIELDS if f"{f}.npy" in first)
    for s, shard in enumerate(self.manifest["shards"]):
      directory = os.path.join(path, shard["name"])
      arrays = {}
      for name in self.fields:
        file = os.path.join(directory, f"{name}.npy")
        if not os.path.exists(file):
          raise MissingFileError(f"missing shard file {file}")
        try:
          arrays[name] = np.load(file, mmap_mode="r")
        except (ValueError, OSError) as e:
          raise DatasetError(f"corrupt shard file {file}: {e}") from e
        rows = arrays[name].shape[0] if arrays[name].ndim else 0
        if rows != shard["samples"]:
          raise DatasetError(f"corrupt shard file {file}: {rows} rows, "
                             f"manifest says {shard['samples']}")
      self._shards.append(arrays)
      if verify:
        self._check_shard(s, force=True)
      rows = np.arange(shard["samples"])
      if split is not None:
        rows = rows[np.asarray(arrays["split"]) == SPLITS[split]]
      index.append(np.stack([np.full(len(rows), s), rows], 1))
    self._index = np.concatenate(index)
    if split is not None and len(self._index) == 0:
      raise DatasetError(f"{path} has no samples in split {split!r}")

  @property
  def name(self) -> str:
    """"split 'val' of PATH" or PATH: what messages call this dataset."""
    return self.path if self.split is None else f"split {self.split!r} of {self.path}"

  @property
  def camera(self) -> dict:
    """The camera of the "image" and "depth" arrays (`dataset.camera`): height, width,
    intrinsics (3, 3), camera_from_world (4, 4), OpenCV axes, and the scene's light_dir
    (`camera.check_camera`). Datasets written before
    the manifest stored it were all rendered by the one fixed camera: it is rebuilt from
    `dataset.camera` at their image size."""
    try:
      cam = self.manifest.get("camera")
      if cam is None:
        size = int(self.manifest["config"]["data"]["image_size"])
        cam = camera.camera_dict(size, size)
      return camera.check_camera(cam)
    except (KeyError, TypeError, ValueError) as e:
      raise DatasetError(f"{self._manifest_path}: no usable camera record "
                         f"({type(e).__name__}: {e})") from e

  @property
  def kind(self) -> str:
    """What the objects are: "towers", "tools" or "pendulum" (`generation.kind_of`; older
    manifests, which did not record it, held towers)."""
    return self.manifest.get("kind", "towers")

  @property
  def engine(self) -> str | None:
    """The backend that simulated the trajectories ("mjx", "box_plane", "mujoco")."""
    return self.manifest.get("engine", {}).get("backend")

  @property
  def pushes(self):
    """The pushes the trajectories were recorded under (`sim.pushes.Pushes`). Datasets
    written before the manifest stored them all used the paper's four."""
    p = self.manifest.get("pushes")
    try:
      return default_pushes() if p is None else pushes_from_record(p)
    except (KeyError, TypeError, ValueError) as e:
      raise DatasetError(f"{self._manifest_path}: no usable pushes record "
                         f"({type(e).__name__}: {e})") from e

  def __len__(self) -> int:
    return len(self._index)

  @property
  def sample_keys(self) -> tuple[str, ...]:
    """What a sample holds: SAMPLE_KEYS and the OPTIONAL_FIELDS this dataset has."""
    return SAMPLE_KEYS + self.fields[len(FIELDS):]

  def _check_shard(self, s: int, force: bool = False) -> None:
    """Raises DatasetError naming the file unless shard s matches its checksums and its
    voxels are 0/1; each shard is checked once per Dataset."""
    with self._lock:
      if s in self._checked and not force:
        return
      shard = self.manifest["shards"][s]
      directory = os.path.join(self.path, shard["name"])
      for name in self.fields:
        file = os.path.join(directory, f"{name}.npy")
        if sha256(file) != shard["files"][f"{name}.npy"]:
          raise DatasetError(f"corrupt shard file {file}: checksum mismatch (regenerate the "
                             "shard: delete its folder and run `python -m ppdjax.generate` "
                             "again)")
      top = int(np.max(self._shards[s]["voxels"], initial=0))
      if top > 1:
        raise DatasetError(f"corrupt shard file {os.path.join(directory, 'voxels.npy')}: "
                           f"occupancy values up to {top}, expected 0 or 1")
      self._checked.add(s)

  def __getitem__(self, i: int) -> dict:
    # bool is an int to Python, and a float used to be cut to an int here: both refused
    if not isinstance(i, numbers.Integral) and np.ndim(i) == 0 and np.issubdtype(
        np.asarray(i).dtype, np.integer):
      i = int(i)  # a 0-d integer array (NumPy's or JAX's)
    if isinstance(i, (bool, np.bool_)) or not isinstance(i, numbers.Integral):
      raise TypeError(f"a dataset index must be an int, got {i!r} ({type(i).__name__}); "
                      "take(indices) reads several samples")
    batch = self.take([i])
    first = lambda v: (Primitives(*[getattr(v, f)[0] for f in primitives.FIELDS])
                       if isinstance(v, Primitives) else v[0])
    return {k: int(v[0]) if k == "tower_id" else first(v) for k, v in batch.items()}

  def take(self, indices, keys=None) -> dict:
    """A batch of samples as stacked arrays (Primitives fields stacked too).

    Args:
      indices: a 1-D sequence of int sample indices in [-len, len) (negative from the
        end). An empty one gives empty (0, ...) arrays of the fields' trailing shapes.
      keys: the sample keys to read (default all; a str names one); others are never
        touched on disk.

    Raises:
      TypeError for indices that are not integers, IndexError naming one out of range,
      KeyError naming an unknown key, DatasetError naming a corrupt shard file.
    """
    arr = np.asarray(indices)
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
      raise TypeError(f"indices must be a 1-D sequence of ints, got a {arr.dtype} array of "
                      f"shape {arr.shape}")
    indices = arr.astype(np.int64)
    outside = indices[(indices < -len(self)) | (indices >= len(self))]
    if outside.size:
      raise IndexError(f"sample index {outside[0]} out of range for the {len(self)} samples "
                       f"of {self.name}")
    keys = (keys,) if isinstance(keys, str) else tuple(keys or self.sample_keys)
    unknown = sorted(set(keys) - set(self.sample_keys))
    if unknown:
      raise KeyError(f"unknown sample keys {unknown}; expected some of {self.sample_keys}")
    names = [f for k in keys for f in (primitives.FIELDS if k == "primitives" else (k,))]
    where = self._index[indices]
    # shaped from the first shard (a directory never mixes configs), so that no indices
    # give (0, ...) arrays of the right trailing shape and dtype
    out = {n: np.empty((len(indices),) + self._shards[0][n].shape[1:],
                       self._shards[0][n].dtype) for n in names}
    for s in np.unique(where[:, 0]):
      self._check_shard(int(s))
      pick = np.nonzero(where[:, 0] == s)[0]
      rows = where[pick, 1]
      order = np.argsort(rows)  # ascending rows: sequential reads of the memory map
      for n in names:
        out[n][pick[order]] = self._shards[s][n][rows[order]]
    batch = {k: out[k] for k in keys if k != "primitives"}
    if "primitives" in keys:
      batch["primitives"] = Primitives(*[out[f] for f in primitives.FIELDS])
    return batch


def open_dataset(path: str, split: str | None = None, verify: bool = False,
                 check: bool = True) -> Dataset:
  """Opens a directory written by `python -m ppdjax.generate` (`Dataset` has the details);
  `split` in {"train", "val", "test"} or None for all; `verify` checks every shard's
  checksums now, `check` (default) each shard's when it is first read.

  Raises MissingFileError (a DatasetError and a FileNotFoundError) or DatasetError naming
  the missing or corrupt file or manifest key; ValueError for another split.
  """
  return Dataset(path, split, verify, check)
