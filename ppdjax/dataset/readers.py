"""Reading a JSON or .npz file with errors that name it: every surface that reads files
(datasets, models, videos' records, example towers) passes its own error types."""

from __future__ import annotations

import json
import os

import numpy as np


def read_json(path: str, *, error: type, missing: type) -> dict:
  """The JSON object in `path`: `missing` if there is no such file, else `error` naming
  the file if it is empty, not UTF-8 JSON, or not an object."""
  if not os.path.exists(path):
    raise missing(f"{path}: no such file")
  try:
    with open(path, encoding="utf-8") as f:
      text = f.read()
    data = json.loads(text) if text.strip() else "empty"
  except (OSError, ValueError) as e:  # a directory, not UTF-8, not JSON
    raise error(f"{path} is corrupt: not valid JSON ({e})") from e
  if not isinstance(data, dict):
    raise error(f"{path} is corrupt: " + ("the file is empty" if data == "empty" else
                                           f"expected a JSON object, got {data!r:.40}"))
  return data


def read_npz(path: str, what: str, *, error: type, missing: type) -> dict:
  """Every array of the .npz archive at `path` (a `what` file, as messages call it), read
  now: a truncated or bit-flipped file fails here naming it (zip keeps a CRC-32 per
  array), not at first use. Raises `missing` if there is no such file, else `error`."""
  if not os.path.exists(path):
    raise missing(f"{path}: no such {what} file")
  bad = lambda why: error(f"{path}: not a readable {what} file: {why}")
  if os.path.isdir(path):
    raise bad("it is a directory, expected an .npz file")
  with open(path, "rb") as f:
    head = f.read(6)
  if head.startswith(b"\x93NUMPY"):
    raise bad("it is an .npy file (one array); expected an .npz archive of named arrays")
  if not head.startswith(b"PK"):
    raise bad("the file is empty" if not head else "not an .npz (zip) archive")
  try:
    with np.load(path) as z:
      return {k: z[k] for k in z.files}
  except Exception as e:  # pylint: disable=broad-except
    # damaged bytes fail in zipfile, zlib or numpy's header parser in many ways (BadZipFile,
    # zlib.error, EOFError, ValueError, NotImplementedError...): all mean a corrupt file
    raise bad(f"the archive is truncated or corrupt ({type(e).__name__}: {e})") from e
