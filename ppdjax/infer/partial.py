"""Resumable evaluation: each batch's records saved as it is made, reused when the same
evaluation runs again (`evaluation.evaluate(partial_dir=...)`).

A folder holds `settings.json` (what the records depend on: model, data, split, objects,
batch size, samples, rows, seed) and one `batch-<first object>.npz` per batch. Records are
`rows.batch_records` dicts keyed by tuples; a file stores its keys as JSON beside the
arrays, so nothing is pickled. Files are written to a temporary name and renamed, so an
interrupted run never leaves a half-written batch; an unreadable batch file is recomputed.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np


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
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, "settings.json")
    settings = json.loads(json.dumps(settings))  # as JSON reads it back
    if os.path.exists(path):
      with open(path) as f:
        saved = json.load(f)
      differ = sorted(k for k in set(saved) | set(settings) if saved.get(k) != settings.get(k))
      if differ:
        raise OtherEvaluation(f"{folder} holds records of another evaluation (settings differ: "
                         f"{', '.join(differ)}); delete the folder or choose another")
    else:
      with open(path, "w") as f:
        json.dump(settings, f, indent=1)

  def _path(self, start: int) -> str:
    return os.path.join(self.folder, f"batch-{start:07d}.npz")

  def load(self, start: int) -> dict | None:
    """The records of the batch that begins at object `start`, or None if not saved (or
    unreadable: it is then recomputed)."""
    path = self._path(start)
    if not os.path.exists(path):
      return None
    try:
      with np.load(path) as f:
        keys = json.loads(str(f["__keys__"]))
        return {tuple(k): f[f"a{i}"] for i, k in enumerate(keys)}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
      return None

  def save(self, start: int, records: dict) -> None:
    keys = list(records)
    arrays = {f"a{i}": np.asarray(records[k]) for i, k in enumerate(keys)}
    tmp = self._path(start) + ".tmp.npz"
    np.savez(tmp, __keys__=np.asarray(json.dumps([list(k) for k in keys])), **arrays)
    os.replace(tmp, self._path(start))

  def count(self) -> int:
    return sum(1 for f in os.listdir(self.folder) if f.startswith("batch-")
               and f.endswith(".npz") and ".tmp" not in f)
