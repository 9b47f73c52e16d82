"""Provenance records: what made a result (commit, versions, device, hashes, headlines).

A result file `X` gets `X.provenance.json` beside it, a result folder `provenance.json` in
it; `python -m ppdjax.report.index` builds the results index from these records.
"""

import dataclasses
import datetime
import hashlib
import importlib.metadata
import json
import os
import platform
import re
import shlex
import subprocess
from collections.abc import Iterable, Mapping
from typing import Any

import jax
import numpy as np
from flax import nnx

RECORD_SUFFIX = ".provenance.json"
FOLDER_RECORD = "provenance.json"
_DISTRIBUTIONS = {"jax": "jax", "jaxlib": "jaxlib", "flax": "flax", "mujoco": "mujoco",
                  "mujoco_mjx": "mujoco-mjx", "numpy": "numpy", "ppdjax": "ppdjax"}
_PACKAGE_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def record_path(result_path: str | os.PathLike) -> str:
  """Where the provenance record of a result file or folder lies."""
  path = os.fspath(result_path).rstrip(os.sep)
  return os.path.join(path, FOLDER_RECORD) if os.path.isdir(path) else path + RECORD_SUFFIX


def result_of(record: str | os.PathLike) -> str:
  """The result file or folder that a provenance record describes."""
  record = os.fspath(record)
  if os.path.basename(record) == FOLDER_RECORD:
    return os.path.dirname(record)
  return record[:-len(RECORD_SUFFIX)]


def read_provenance(path: str | os.PathLike) -> dict[str, Any]:
  """The record at `path`, or the record of the result file or folder at `path`."""
  path = os.fspath(path)
  if not (path.endswith(RECORD_SUFFIX) or os.path.basename(path) == FOLDER_RECORD):
    path = record_path(path)
  with open(path, encoding="utf-8") as f:
    return json.load(f)


def read_key(result_path: str | os.PathLike, key: str) -> int | float:
  """The number at `key` of a result JSON file.

  Args:
    result_path: a JSON file, or a folder: then the key's first segments name a JSON file
      in it ("test/results.json/table2/PPD/top1").
    key: '/'-separated dict keys and list indices; a dict key holding '/' is matched whole.

  Raises:
    ValueError: naming the key, when the file lacks it or holds no number there.
  """
  parts, path = key.split("/"), os.fspath(result_path)
  while os.path.isdir(path) and parts:
    path = os.path.join(path, parts.pop(0))
  if not os.path.isfile(path):
    raise ValueError(f"headline key {key!r}: no result file {path}")
  with open(path, encoding="utf-8") as f:
    node = json.load(f)
  while parts:
    found = isinstance(node, dict) and next(  # the longest key that fits
        (n for n in range(len(parts), 0, -1) if "/".join(parts[:n]) in node), 0)
    if found:
      node, parts = node["/".join(parts[:found])], parts[found:]
    elif isinstance(node, list) and re.fullmatch(r"\d+", parts[0]) and int(parts[0]) < len(node):
      node = node[int(parts.pop(0))]
    else:
      raise ValueError(f"headline key {key!r}: {path} has no {parts[0]!r} there")
  if isinstance(node, bool) or not isinstance(node, (int, float)):
    raise ValueError(f"headline key {key!r}: {path} holds {node!r} there, not a number")
  return node


def config_hash(config: Any) -> str | None:
  """sha256 of the canonical JSON of a dict, ml_collections ConfigDict or dataclass."""
  if config is None:
    return None
  text = json.dumps(_plain(config), sort_keys=True, separators=(",", ":"), default=_plain)
  return hashlib.sha256(text.encode()).hexdigest()


def weights_hash(weights: Any) -> str | None:
  """sha256 of a model's weights: an nnx.Module's state, or a weights file or folder.

  A folder hashes each file's path relative to it and its bytes, in sorted order (a renamed
  file changes what a restore reads). A module hashes each variable's path, dtype, shape and
  bytes, sorted by path, all but the RNG state (its counters move with every call).
  """
  if weights is None:
    return None
  digest = hashlib.sha256()
  if isinstance(weights, (str, os.PathLike)):
    root = os.fspath(weights)
    files = [root] if os.path.isfile(root) else [
        os.path.join(d, f) for d, _, names in os.walk(root) for f in names]
    if not files:
      raise ValueError(f"no weights files at {root}")
    for path in sorted(files, key=lambda p: os.path.relpath(p, root)):
      with open(path, "rb") as f:
        digest.update(os.path.relpath(path, root).encode() + b"\0" + f.read())
    return digest.hexdigest()
  leaves = jax.tree_util.tree_flatten_with_path(nnx.state(weights, nnx.Not(nnx.RngState)))[0]
  for name, leaf in sorted(((jax.tree_util.keystr(p), v) for p, v in leaves), key=lambda t: t[0]):
    array = np.ascontiguousarray(np.asarray(leaf))
    digest.update(f"{name}:{array.dtype}:{array.shape}".encode() + b"\0" + array.tobytes())
  return digest.hexdigest()


def write_provenance(result_path: str | os.PathLike, *, command: str | Iterable[str],
                     config: Any = None, weights: Any = None,
                     headlines: Mapping[str, str] | None = None,
                     extra: Mapping[str, Any] | None = None) -> str:
  """Writes the provenance record of a result file or folder; returns the record's path.

  Args:
    result_path: the result file or folder, already written.
    command: the command line that made it (a string, or argv as a list).
    config: the run's config (dict, ConfigDict or dataclass), hashed; None: null.
    weights: the model (an nnx.Module) or its weights file or folder, hashed; None: null.
    headlines: name -> key into the result (see `read_key`), each value read now.
    extra: anything else worth keeping, stored under "extra".

  Raises:
    ValueError: a headline key the result does not hold (then nothing is written).
  """
  headline_list = [{"name": n, "key": k, "value": read_key(result_path, k)}  # first: a bad
                   for n, k in (headlines or {}).items()]  # key must leave no record behind
  commit, dirty = _git_state(result_path)
  return _write(record_path(result_path), {
      "created": _utc(),
      "command": command if isinstance(command, str) else shlex.join(command),
      "result": os.path.basename(os.fspath(result_path).rstrip(os.sep)),
      "commit": commit, "dirty": dirty, "versions": _versions(), "device": _device(),
      "config_hash": config_hash(config), "weights_hash": weights_hash(weights),
      "headlines": headline_list, "extra": dict(extra) if extra else None})


def row_headlines(table: dict, prefix: str, rows: Iterable[str],
                  metrics: Iterable[str] = ("top1", "top10", "rmse")) -> dict[str, str]:
  """Headline keys (name -> key) of a results table's rows that exist: each metric with
  its 95 % interval ("ci95"), e.g. row_headlines(r["table2"], "table2", ["PPD"])."""
  units = {"top1": "top-1 (%)", "top10": "top-10 (%)", "rmse": "RMSE (slots)"}
  out = {}
  for row in rows:
    for m in metrics if row in table else ():
      name = f"{row} {units.get(m, m)}"
      out[name] = f"{prefix}/{row}/{m}"
      if m in table[row].get("ci95", {}):
        out[f"{name}, 95 % CI low"] = f"{prefix}/{row}/ci95/{m}/0"
        out[f"{name}, 95 % CI high"] = f"{prefix}/{row}/ci95/{m}/1"
  return out


def backfill(result_json: str | os.PathLike, *, headlines: Mapping[str, str],
             command: str | None = None, device: str | None = None) -> str:
  """Writes the record of a result made before records were; returns the record's path.

  Commit, date, command, versions and device come from git and from the file, null where
  they say nothing: an old result is never given today's versions or device.

  Args:
    result_json: the result file.
    headlines: as `write_provenance`'s.
    command: the command, when the file's "command" field does not say (e.g. a README does).
    device: the device, when the file does not name it but notes beside it do
      ("1 x NVIDIA H100 80GB HBM3").
  """
  with open(result_json, encoding="utf-8") as f:
    data = json.load(f)
  where, name = os.path.split(os.path.abspath(result_json))
  log = (_git(where, "log", "-1", "--format=%H %cI", "--", name) or "").split()
  status = _git(where, "status", "--porcelain", "--", name) if log else None
  scopes = [s for s in (data.get("versions"), data.get("meta"), data) if isinstance(s, dict)]
  recorded = lambda k: next((s[k] for s in scopes if isinstance(s.get(k), str)), None)
  device = _parse_device(device or recorded("device") or recorded("machine") or _steps(data))
  return _write(record_path(result_json), {
      "created": _utc(datetime.datetime.fromisoformat(log[1])) if log else None,
      "command": command or (data.get("command") or "").strip() or None, "result": name,
      "commit": log[0] if log else None, "dirty": None if status is None else bool(status),
      "versions": {k: recorded(k) for k in ("python", *_DISTRIBUTIONS)},
      "device": device,
      "config_hash": None, "weights_hash": None, "headlines": [
          {"name": n, "key": k, "value": read_key(result_json, k)} for n, k in headlines.items()],
      "extra": {"backfilled": _utc(), "note": (
          "commit: the last that changed the file; created: that commit's date; command, "
          "versions and device: as the file or the notes beside it record them, else null")}})


def _plain(obj: Any) -> Any:
  """A JSON-able form of a config, or of a value inside one."""
  if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
    return dataclasses.asdict(obj)
  if hasattr(obj, "to_dict"):  # ml_collections' ConfigDict and FrozenConfigDict
    return obj.to_dict()
  if isinstance(obj, Mapping):
    return dict(obj)
  return obj.tolist() if hasattr(obj, "tolist") else str(obj)  # arrays; enums, paths


def _git(cwd: str, *args: str) -> str | None:
  """A git command's output, or None: a missing git or a non-checkout never fails a write."""
  try:
    done = subprocess.run(["git", "-C", cwd, *args], capture_output=True, text=True,
                          timeout=10, check=False)
  except (OSError, subprocess.SubprocessError):
    return None
  return done.stdout if done.returncode == 0 else None


def _git_state(result_path) -> tuple[str | None, bool | None]:
  """(commit, dirty) of the repository that holds the package; (None, None) outside one."""
  head = (_git(_PACKAGE_DIR, "rev-parse", "HEAD", "--show-toplevel") or "").split("\n")
  status = _git(_PACKAGE_DIR, "status", "--porcelain", "--untracked-files=all")
  if len(head) < 2 or status is None:
    return None, None
  rel = os.path.relpath(os.path.realpath(result_path), os.path.realpath(head[1]))
  here = rel if os.path.isdir(result_path) else os.path.dirname(rel)
  # Untracked files in scratch folders, the compilation cache or beside the result are
  # outputs of this run or others, not inputs; records and the index describe results.
  outputs = ("out/", ".jax_cache/", here.rstrip("/") + "/")
  dirty = any(not ((line.startswith("??") and line[3:].startswith(outputs))
                   or line.strip('"').endswith((RECORD_SUFFIX, "/" + FOLDER_RECORD, "INDEX.md")))
              for line in status.splitlines())
  return head[0], dirty


def _versions() -> dict[str, str | None]:
  versions = {"python": platform.python_version()}
  for key, distribution in _DISTRIBUTIONS.items():
    try:
      versions[key] = importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
      versions[key] = None
  return versions


def _device() -> dict[str, Any] | None:
  try:
    devices = jax.devices()
  except RuntimeError:  # no backend would start: the record still says everything else
    return None
  return {"backend": jax.default_backend(), "kind": devices[0].device_kind,
          "count": len(devices)}


def _steps(data: dict[str, Any]) -> str | None:
  """The device an old pipeline's evaluate steps name, if they agree on one."""
  steps = data.get("steps") if isinstance(data.get("steps"), dict) else {}
  steps = steps.get("steps", steps)  # the video pipeline nests its step list once more
  seen = {s.get("device") for n, s in steps.items() if n.startswith("evaluate")}
  return seen.pop() if len(seen) == 1 else None


def _parse_device(text: str | None) -> dict[str, Any] | None:
  """{backend, kind, count} from "1 x NVIDIA H100 80GB HBM3" or "one NVIDIA H200"."""
  match = re.fullmatch(r"(?:(\d+|one) (?:x )?)?(.+)", (text or "").strip(), re.I)
  count = match and match[1] and (1 if match[1].lower() == "one" else int(match[1]))
  return {"backend": None, "kind": match[2], "count": count or None} if text else None


def _utc(when: datetime.datetime | None = None) -> str:
  """`when` (default: now) in ISO 8601, UTC, to the second."""
  when = when or datetime.datetime.now(datetime.timezone.utc)
  return when.astimezone(datetime.timezone.utc).isoformat(timespec="seconds")


def _write(path: str, record: dict[str, Any]) -> str:
  # Through a temporary file, so that a reader (the index) never sees half a record.
  with open(path + ".tmp", "w", encoding="utf-8") as f:
    f.write(json.dumps(record, indent=1) + "\n")
  os.replace(path + ".tmp", path)
  return path
