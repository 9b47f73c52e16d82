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
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
from typing import Iterator

import numpy as np

from ppdjax.conventions import OBS_KEYS
from ppdjax import primitives
from ppdjax.dataset import camera
from ppdjax.primitives import Primitives
from ppdjax.sim.pushes import RESTITUTION, Pushes, default_pushes

FORMAT_VERSION = 1
# One .npy file per field: the observations, depth, the Primitives fields, and labels.
FIELDS = OBS_KEYS + ("depth",) + primitives.FIELDS + ("materials", "tower_id", "split")
SAMPLE_KEYS = OBS_KEYS + ("depth", "primitives", "materials", "tower_id")  # what a sample holds
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
  tmp = directory + ".tmp"
  os.makedirs(tmp, exist_ok=True)
  sums = {}
  try:
    for name in FIELDS:
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
  with open(done) as f:
    sums = json.load(f)
  for name, digest in sums.items():
    path = os.path.join(directory, name)
    if not os.path.exists(path) or sha256(path) != digest:
      return None
  return sums


class Dataset:
  """Random access to samples of a generated dataset (memory-mapped, nothing loaded).

  `len(ds)` samples; `ds[i]` is a dict with the keys SAMPLE_KEYS: "voxels" (32,32,32)
  uint8, "image" (H,W,3) uint8, "trajectories" (P,256,7) float32, "depth" (H,W) float32,
  "primitives" Primitives (K = 5, valid mask), "materials" (5,) int (-1 padding),
  "tower_id" int.

  Args:
    path: the dataset directory.
    split: "train", "val", "test" or None (all samples).
    verify: check every shard's checksums now.
    check: check a shard's checksums and voxel values when this object first reads it.
  """

  def __init__(self, path: str, split: str | None = None, verify: bool = False,
               check: bool = True):
    manifest_path = os.path.join(path, "manifest.json")
    if not os.path.isdir(path):
      raise DatasetError(f"no dataset directory at {path}")
    if not os.path.exists(manifest_path):
      raise DatasetError(f"{manifest_path} is missing: generation did not finish "
                         "(run `python -m ppdjax.generate` again to resume it)")
    try:
      with open(manifest_path) as f:
        self.manifest = json.load(f)
    except json.JSONDecodeError as e:
      raise DatasetError(f"{manifest_path} is corrupt: {e}") from e
    if self.manifest.get("format_version") != FORMAT_VERSION:
      raise DatasetError(f"{manifest_path}: format version "
                         f"{self.manifest.get('format_version')} != {FORMAT_VERSION}")
    if split is not None and split not in SPLITS:
      raise ValueError(f"split must be one of {tuple(SPLITS)} or None, got {split!r}")
    self.path = path
    self._checked = set() if check else set(range(len(self.manifest["shards"])))
    self._lock = threading.Lock()
    self._shards, index = [], []
    for s, shard in enumerate(self.manifest["shards"]):
      directory = os.path.join(path, shard["name"])
      arrays = {}
      for name in FIELDS:
        file = os.path.join(directory, f"{name}.npy")
        if not os.path.exists(file):
          raise DatasetError(f"missing shard file {file}")
        try:
          arrays[name] = np.load(file, mmap_mode="r")
        except (ValueError, OSError) as e:
          raise DatasetError(f"corrupt shard file {file}: {e}") from e
        if len(arrays[name]) != shard["samples"]:
          raise DatasetError(f"corrupt shard file {file}: {len(arrays[name])} rows, "
                             f"manifest says {shard['samples']}")
      self._shards.append(arrays)
      if verify:
        self._check_shard(s, force=True)
      rows = np.arange(shard["samples"])
      if split is not None:
        rows = rows[np.asarray(arrays["split"]) == SPLITS[split]]
      index.append(np.stack([np.full(len(rows), s), rows], 1))
    self._index = np.concatenate(index) if index else np.zeros((0, 2), np.int64)
    if split is not None and len(self._index) == 0:
      raise DatasetError(f"{path} has no samples in split {split!r}")

  @property
  def camera(self) -> dict:
    """The camera of the "image" and "depth" arrays (`dataset.camera`): height, width,
    intrinsics (3, 3), camera_from_world (4, 4), OpenCV axes, and the scene's light_dir
    (`camera.check_camera`). Datasets written before
    the manifest stored it were all rendered by the one fixed camera: it is rebuilt from
    `dataset.camera` at their image size."""
    cam = self.manifest.get("camera")
    if cam is None:
      size = int(self.manifest["config"]["data"]["image_size"])
      cam = camera.camera_dict(size, size)
    return camera.check_camera(cam)

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
    return default_pushes() if p is None else pushes_from_record(p)

  def __len__(self) -> int:
    return len(self._index)

  def _check_shard(self, s: int, force: bool = False) -> None:
    """Raises DatasetError naming the file unless shard s matches its checksums and its
    voxels are 0/1; each shard is checked once per Dataset."""
    with self._lock:
      if s in self._checked and not force:
        return
      shard = self.manifest["shards"][s]
      directory = os.path.join(self.path, shard["name"])
      for name in FIELDS:
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
    if not -len(self) <= i < len(self):
      raise IndexError(f"sample {i} out of range for {len(self)} samples")
    batch = self.take([i])
    first = lambda v: (Primitives(*[getattr(v, f)[0] for f in primitives.FIELDS])
                       if isinstance(v, Primitives) else v[0])
    return {k: int(v[0]) if k == "tower_id" else first(v) for k, v in batch.items()}

  def take(self, indices, keys=None) -> dict:
    """A batch of samples as stacked arrays (Primitives fields stacked too).

    Args:
      indices: sample indices.
      keys: the sample keys to read (default all); others are never touched on disk.
    """
    indices = np.asarray(indices, np.int64)
    if indices.size and not (-len(self) <= indices.min() and indices.max() < len(self)):
      raise IndexError(f"sample indices out of range for {len(self)} samples")
    keys = tuple(keys or SAMPLE_KEYS)
    unknown = sorted(set(keys) - set(SAMPLE_KEYS))
    if unknown:
      raise KeyError(f"unknown sample keys {unknown}; expected some of {SAMPLE_KEYS}")
    names = [f for k in keys for f in (primitives.FIELDS if k == "primitives" else (k,))]
    where = self._index[indices]
    out = {n: None for n in names}
    for s in np.unique(where[:, 0]):
      self._check_shard(int(s))
      pick = np.nonzero(where[:, 0] == s)[0]
      rows = where[pick, 1]
      order = np.argsort(rows)  # ascending rows: sequential reads of the memory map
      for n in names:
        part = np.asarray(self._shards[s][n][rows[order]])
        if out[n] is None:
          out[n] = np.empty((len(indices),) + part.shape[1:], part.dtype)
        out[n][pick[order]] = part
    batch = {k: out[k] for k in keys if k != "primitives"}
    if "primitives" in keys:
      batch["primitives"] = Primitives(*[out[f] for f in primitives.FIELDS])
    return batch


def open_dataset(path: str, split: str | None = None, verify: bool = False,
                 check: bool = True) -> Dataset:
  """Opens a generated dataset; `split` in {"train", "val", "test"} or None for all.

  `verify` checks every shard's checksums now; `check` (default) checks each shard when
  it is first read. Raises DatasetError naming the missing or corrupt file.
  """
  return Dataset(path, split, verify, check)


def batches(dataset: Dataset, batch_size: int, *, seed: int, epoch: int = 0,
            start: int = 0, drop_remainder: bool = True,
            part: tuple[int, int] = (0, 1), keys=None) -> Iterator[dict]:
  """Shuffled batches of one epoch, deterministic in (seed, epoch), read lazily.

  Args:
    dataset: a Dataset.
    batch_size: samples per batch.
    seed, epoch: the permutation is `default_rng([seed, epoch]).permutation(len)`.
    start: first batch to yield (resume mid-epoch).
    drop_remainder: skip a last, smaller batch.
    part: (i, n): read only the i-th of n equal slices of each batch (process i of n in a
      multi-host run); batch_size must divide by n.
    keys: sample keys to read (default all).

  Yields:
    dicts of stacked arrays (Primitives fields stacked too).
  """
  if batch_size < 1:
    raise ValueError(f"batch_size must be >= 1, got {batch_size}")
  index, count = part
  if batch_size % count or not 0 <= index < count:
    raise ValueError(f"part={part} must split batch_size={batch_size} into equal slices")
  order = np.random.default_rng([seed, epoch]).permutation(len(dataset))
  stop = len(order) - (len(order) % batch_size if drop_remainder else 0)
  for b in range(start * batch_size, stop, batch_size):
    rows = order[b:b + batch_size]
    rows = np.array_split(rows, count)[index] if count > 1 else rows
    yield dataset.take(rows, keys)
