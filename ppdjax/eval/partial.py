"""Resumable evaluation: each batch's records saved as it is made, reused when the same
evaluation runs again (`evaluation.evaluate(partial_dir=...)`).

A folder holds `settings.json` (what the records depend on: a hash of the model's weights,
the data, split and objects, batch size, samples, rows, seed, the record layout's version
and the backend), written with the first batch, and one `batch-<first object>.npz` per
batch. Records are
`rows.batch_records` dicts keyed by tuples; a file stores its keys as JSON beside the
arrays, so nothing is pickled. Files are written to a temporary name and renamed, so an
interrupted run never leaves a half-written batch; an unreadable batch file is recomputed.
"""

from __future__ import annotations

import io
import json
import os
import zipfile

import numpy as np

# eval settings added after records were saved, with the value older records ran as
UNSET_BEFORE = {"network_prior_weight": -1.0}


class EvaluationPaused(Exception):
  """`evaluate` stopped after its time budget: `done` of `total` objects are saved in
  `folder`; calling it again with the same settings goes on from there."""

  def __init__(self, done: int, total: int, folder: str):
    super().__init__(f"evaluated {done} of {total} objects; their records are in {folder}: "
                     "run the same evaluation again to go on")
    self.done, self.total, self.folder = done, total, folder


class OtherEvaluation(ValueError):
  """The folder holds the records of an evaluation with other settings."""


class PartialRecords:
  """The saved batches of one evaluation (see the module docstring)."""

  def __init__(self, folder: str, settings: dict):
    self.folder = folder
    self.settings = json.loads(json.dumps(settings))  # as JSON reads it back
    path = os.path.join(folder, "settings.json")
    if os.path.exists(path):
      try:
        with open(path) as f:
          saved = json.load(f)
      except (OSError, ValueError):
        saved = None  # unreadable: only a crash while writing it leaves one
      if saved is None and self.count():
        raise OtherEvaluation(f"{path} is unreadable and batch records lie beside it: "
                              "delete the folder to start again")
      # a key the saved records predate ran as the schema's default (what it was added as)
      old = lambda k: saved.get(k, UNSET_BEFORE.get(k))
      differ = [] if saved is None else sorted(
          k for k in set(saved) | set(self.settings) if old(k) != self.settings.get(k))
      if differ:
        raise OtherEvaluation(f"{folder} holds records of another evaluation (settings "
                              f"differ: {', '.join(differ)}); delete the folder or choose "
                              "another")

  def _path(self, start: int) -> str:
    return os.path.join(self.folder, f"batch-{start:07d}.npz")

  def load(self, start: int) -> dict | None:
    """The records of the batch that begins at object `start`, or None if not saved (or
    unreadable: it is then recomputed)."""
    path = self._path(start)
    return _read(path) if os.path.exists(path) else None

  def save(self, start: int, records: dict) -> None:
    """Saves one batch (and, with the first, the settings): written whole or not at all."""
    os.makedirs(self.folder, exist_ok=True)
    settings = os.path.join(self.folder, "settings.json")
    if not os.path.exists(settings):
      _write_atomic(settings, json.dumps(self.settings, indent=1).encode())
    _write_records(self._path(start), records, compressed=False)

  def count(self) -> int:
    return len(_batch_files(self.folder))


RECORDS_FILE = "records.npz"  # a folder's batches in one compressed file (`compact`)


def saved_records(folder: str) -> dict:
  """Every batch saved in `folder`, concatenated in object order, or its compacted
  RECORDS_FILE (the per-object records of an evaluation kept with `--keep_records`);
  ValueError if none or one is unreadable, or if the folder holds both (an evaluation
  run again on a compacted folder, perhaps interrupted: which records are whole is not
  known)."""
  files = _batch_files(folder)
  compacted = os.path.exists(os.path.join(folder, RECORDS_FILE))
  if files and compacted:
    raise ValueError(f"{folder} holds both {RECORDS_FILE} and {len(files)} batch files of an "
                     "evaluation run on it again: finish that evaluation (it compacts its "
                     f"batches in place of {RECORDS_FILE}) or delete one of them")
  if compacted:
    records = _read(os.path.join(folder, RECORDS_FILE))
    if records is None:
      raise ValueError(f"{os.path.join(folder, RECORDS_FILE)} cannot be read")
    return records
  batches = [_read(os.path.join(folder, f)) for f in files]
  if not batches or any(b is None for b in batches):
    raise ValueError(f"{folder} holds no readable batch records"
                     + (f" ({sum(b is None for b in batches)} unreadable)" if batches else ""))
  keys = set.intersection(*(set(b) for b in batches))
  return {k: np.concatenate([b[k] for b in batches]) for k in keys}


def compact(folder: str) -> str:
  """Replaces `folder`'s batch files by one compressed RECORDS_FILE (about a tenth of their
  size: records small enough to keep beside the results) and returns its path;
  `saved_records` reads it, settings.json stays. A compacted folder resumes nothing: an
  evaluation run on it again computes every batch, and compacting those replaces the file
  (call it once an evaluation has written its results: its batches are then whole)."""
  path = os.path.join(folder, RECORDS_FILE)
  if _batch_files(folder) and os.path.exists(path):
    os.remove(path)  # superseded by the batches of the evaluation run again
  _write_records(path, saved_records(folder), compressed=True)
  for f in _batch_files(folder):
    os.remove(os.path.join(folder, f))
  return path


def _batch_files(folder: str) -> list[str]:
  if not os.path.isdir(folder):
    return []
  return sorted(f for f in os.listdir(folder) if f.startswith("batch-") and f.endswith(".npz"))


def _write_records(path: str, records: dict, compressed: bool) -> None:
  """Records keyed by tuples as one .npz (`_read` reads it back), written whole or not at
  all: the keys as JSON, the arrays as a0, a1, ..."""
  keys = list(records)
  buf = io.BytesIO()
  (np.savez_compressed if compressed else np.savez)(
      buf, __keys__=np.asarray(json.dumps([list(k) for k in keys])),
      **{f"a{i}": np.asarray(records[k]) for i, k in enumerate(keys)})
  _write_atomic(path, buf.getvalue())


def _read(path: str) -> dict | None:
  """One batch file's records, or None if it cannot be read."""
  try:
    with np.load(path) as f:
      keys = json.loads(str(f["__keys__"]))
      return {tuple(k): f[f"a{i}"] for i, k in enumerate(keys)}
  except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
    return None


def _write_atomic(path: str, data: bytes) -> None:
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    f.write(data)
    f.flush()
    os.fsync(f.fileno())
  os.replace(tmp, path)
