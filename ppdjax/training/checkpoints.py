"""Orbax checkpoints of a training run, and `load(workdir)` for inference and notebooks.

A workdir holds `config.json` (the preset the run was made with, read back through
`configs.schema`), `decompose.json` (its decomposition settings and the camera of its
training data: what `make_decompose_fn(workdir)` runs), `checkpoints/` (the last few:
model and optimizer, for exact resume) and `best/` (the model with the lowest validation
loss). `export` writes a model to ship instead: `config.json`, `decompose.json`,
`export.json` and its weights as `weights-NN.npz` files of bounded size; `load` reads both
layouts.
"""

from __future__ import annotations

import hashlib
import json
import os
import re

import jax
import ml_collections
import numpy as np
import orbax.checkpoint as ocp
from flax import nnx

from ppdjax.configs import schema
from ppdjax.nn.model import PPD

LATEST, BEST = "checkpoints", "best"
EXPORT = "export.json"
DECOMPOSE_FILE = "decompose.json"


class CheckpointError(ValueError):
  """A workdir without a usable checkpoint or config."""


def managers(workdir: str, keep: int) -> tuple[ocp.CheckpointManager, ocp.CheckpointManager]:
  """(latest, best): the last `keep` checkpoints, and the best one by validation loss."""
  workdir = os.path.abspath(workdir)
  latest = ocp.CheckpointManager(
      os.path.join(workdir, LATEST), item_names=("model", "optimizer"),
      options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True))
  best = ocp.CheckpointManager(
      os.path.join(workdir, BEST), item_names=("model",),
      options=ocp.CheckpointManagerOptions(max_to_keep=1, create=True, best_mode="min",
                                           best_fn=lambda m: m["val_loss"]))
  return latest, best


def save(latest, best, step: int, model_state, opt_state, val_loss: float | None) -> None:
  """Saves the run (and, with a validation loss, offers the model to the best manager)."""
  pure = nnx.to_pure_dict
  latest.save(step, args=ocp.args.Composite(model=ocp.args.StandardSave(pure(model_state)),
                                            optimizer=ocp.args.StandardSave(pure(opt_state))))
  if val_loss is not None:
    best.save(step, args=ocp.args.Composite(model=ocp.args.StandardSave(pure(model_state))),
              metrics={"val_loss": float(val_loss)})


def restore(manager, step: int, **abstract_states):
  """Restores the named nnx States (given as abstract targets) from `step`.

  Raises:
    CheckpointError naming the step and, where the storage layer says, the file, for a
    checkpoint that cannot be read (truncated or corrupt files).
  """
  args = {k: ocp.args.StandardRestore(nnx.to_pure_dict(v)) for k, v in abstract_states.items()}
  try:
    restored = manager.restore(step, args=ocp.args.Composite(**args))
  except Exception as e:  # TensorStore, orbax and OS errors alike: say which step and file
    raise CheckpointError(_unreadable(manager, step, e)) from e
  out = {}
  for k, v in abstract_states.items():
    state = jax.tree.map(lambda x: x, v)
    nnx.replace_by_pure_dict(state, restored[k])
    out[k] = state
  return out


UNREADABLE = "unreadable_checkpoints"


def set_aside(manager, steps, workdir: str) -> str:
  """Moves unreadable steps out of the manager's folder (to WORKDIR/unreadable_checkpoints/),
  so training can save those steps again; returns where they went."""
  target = os.path.join(workdir, UNREADABLE)
  os.makedirs(target, exist_ok=True)
  for step in steps:
    src = os.path.join(str(manager.directory), str(step))
    dst = os.path.join(target, str(step))
    n = 1
    while os.path.exists(dst):
      dst, n = os.path.join(target, f"{step}-{n}"), n + 1
    os.replace(src, dst)
  manager.reload()
  return target


def _unreadable(manager, step: int, error: Exception) -> str:
  """'checkpoint step N in DIR is unreadable: FILE (first line of the error)'."""
  text = str(error)
  files = re.findall(r"(?:file://)?(/[^\s\"',\]]+)", text)
  where = f"{files[-1]} " if files else ""
  first = text.strip().splitlines()[0][:300] if text.strip() else type(error).__name__
  return (f"checkpoint step {step} in {manager.directory} is unreadable: {where}"
          f"({type(error).__name__}: {first})")


def save_config(workdir: str, config: ml_collections.ConfigDict,
                camera: dict | None = None) -> None:
  """config.json, and decompose.json: the decomposition settings of its `eval` section
  and `camera` (None: the datasets' camera at the data's image size)."""
  from ppdjax.dataset.camera import camera_dict  # pylint: disable=import-outside-toplevel
  from ppdjax.infer.config import DecomposeConfig  # pylint: disable=import-outside-toplevel
  os.makedirs(workdir, exist_ok=True)
  with open(os.path.join(workdir, "config.json"), "w") as f:
    f.write(config.to_json_best_effort(indent=1, sort_keys=True))
  size = config.data.image_size
  camera = camera_dict(size, size) if camera is None else camera
  try:  # a run whose eval section cannot decompose is refused before it trains
    settings = DecomposeConfig.from_eval(config.eval)
  except ValueError as e:
    raise schema.ConfigError(f"config.eval: {e} (fit.* is eval.fit, eval.image_fit, "
                             "eval.depth, eval.face_spread)") from e
  record = {"config": settings.to_dict(),
            "camera": {k: np.asarray(v).tolist() if v is not None else None
                       for k, v in camera.items()}}
  with open(os.path.join(workdir, DECOMPOSE_FILE), "w") as f:
    json.dump(record, f, indent=1)


def read_decompose(workdir: str) -> dict | None:
  """decompose.json of a workdir or export ({"config": DecomposeConfig, "camera": dict}),
  or None for a run saved before it existed."""
  from ppdjax.infer.config import DecomposeConfig  # pylint: disable=import-outside-toplevel
  path = os.path.join(workdir, DECOMPOSE_FILE)
  if not os.path.exists(path):
    return None
  try:
    with open(path) as f:
      record = json.load(f)
    return {"config": DecomposeConfig.from_dict(record["config"]), "camera": record["camera"]}
  except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
    raise CheckpointError(f"{path} is corrupt: {e}") from e


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """A run's config.json through the schema: keys it predates take the behaviour they
  had (`schema.complete`); an unknown or ill-typed key is named."""
  path = os.path.join(workdir, "config.json")
  if not os.path.exists(path):
    raise CheckpointError(f"{workdir} is not a training workdir: {path} is missing")
  try:
    with open(path) as f:
      saved = _lists_to_tuples(json.load(f))
  except json.JSONDecodeError as e:
    raise CheckpointError(f"{path} is corrupt: {e}") from e
  try:
    return schema.complete_saved(saved)
  except schema.ConfigError as e:
    raise CheckpointError(f"{path}: {e}") from e


def _lists_to_tuples(d):
  if isinstance(d, dict):
    return {k: _lists_to_tuples(v) for k, v in d.items()}
  return tuple(d) if isinstance(d, list) else d


def load(workdir: str, which: str = "best"):
  """The trained model of a workdir, in eval mode, and its config.

  Args:
    workdir: a directory written by `python -m ppdjax.train`, or a model written by
      `export` (such as the one shipped in assets/).
    which: "best" (lowest validation loss) or "latest".

  Returns:
    (model, config): a `ppdjax.nn.model.PPD` and the run's ConfigDict.

  Raises:
    CheckpointError naming what is missing.
  """
  if which not in (BEST, "latest"):
    raise ValueError(f"which must be 'best' or 'latest', got {which!r}")
  config = read_config(workdir)
  if os.path.exists(os.path.join(workdir, EXPORT)):
    return _load_export(workdir, config), config
  folder = os.path.join(os.path.abspath(workdir), BEST if which == BEST else LATEST)
  if not os.path.isdir(folder):
    raise CheckpointError(f"{workdir} has no checkpoint: {folder} is missing")
  manager = ocp.CheckpointManager(folder, item_names=("model",) if which == BEST else
                                  ("model", "optimizer"),
                                  options=ocp.CheckpointManagerOptions(create=False))
  try:
    step = manager.latest_step()
    if step is None:
      raise CheckpointError(f"{workdir} has no checkpoint: {folder} is empty")
    graphdef, abstract = _abstract_model(config)
    state = restore(manager, step, model=abstract)["model"]
  finally:
    manager.close()
  return nnx.merge(graphdef, state), config  # call sites pass train=False unless training


def _abstract_model(config):
  return nnx.split(nnx.eval_shape(lambda: PPD(config.model, rngs=nnx.Rngs(0))))


def _flat(tree, prefix=""):
  """{'a/b/0': leaf} of a nested dict (nnx pure dicts key lists by int)."""
  out = {}
  for k, v in tree.items():
    out.update(_flat(v, f"{prefix}{k}/") if isinstance(v, dict) else {f"{prefix}{k}": v})
  return out


def export(workdir: str, out: str, *, dtype: str = "float16", max_file_mb: float = 15.0,
           which: str = "best") -> dict:
  """Writes a trained model to ship: config.json, export.json and weights-NN.npz files.

  Args:
    workdir: a training workdir.
    out: the folder to write (created).
    dtype: storage type of floating-point weights ("float16" halves the size; `load`
      casts back to float32).
    max_file_mb: no weights file is larger than this (MiB).
    which: "best" or "latest".

  Returns:
    the export.json record: files with sizes and sha256, dtype, parameter count.
  """
  model, config = load(workdir, which)
  arrays = {k: np.asarray(v) for k, v in _flat(nnx.to_pure_dict(nnx.state(model))).items()}
  arrays = {k: v.astype(dtype) if np.issubdtype(v.dtype, np.floating) else v
            for k, v in arrays.items()}
  limit = max_file_mb * 2 ** 20
  cost = lambda k: arrays[k].nbytes + 512  # with the npz container's per-array overhead
  big = max(arrays, key=cost)
  if cost(big) > limit:
    raise ValueError(f"{big} alone takes {arrays[big].nbytes / 2 ** 20:.2f} MiB, more than "
                     f"max_file_mb={max_file_mb}")
  groups, size = [[]], 0
  for k in sorted(arrays):
    if groups[-1] and size + cost(k) > limit:
      groups.append([])
      size = 0
    groups[-1].append(k)
    size += cost(k)
  os.makedirs(out, exist_ok=True)
  files = []
  for i, keys in enumerate(groups):
    name = f"weights-{i:02d}.npz"
    path = os.path.join(out, name)
    np.savez(path, **{k: arrays[k] for k in keys})
    with open(path, "rb") as f:
      digest = hashlib.sha256(f.read()).hexdigest()
    files.append({"name": name, "bytes": os.path.getsize(path), "sha256": digest})
  save_config(out, config, (read_decompose(workdir) or {}).get("camera"))
  record = {"dtype": dtype, "parameters": int(sum(v.size for v in arrays.values())),
            "files": files, "source": os.path.basename(os.path.normpath(workdir))}
  with open(os.path.join(out, EXPORT), "w") as f:
    json.dump(record, f, indent=1)
  return record


def _load_export(folder: str, config):
  with open(os.path.join(folder, EXPORT)) as f:
    record = json.load(f)
  arrays = {}
  for entry in record["files"]:
    path = os.path.join(folder, entry["name"])
    if not os.path.exists(path):
      raise CheckpointError(f"{folder}: weights file {entry['name']} is missing")
    with open(path, "rb") as f:
      if hashlib.sha256(f.read()).hexdigest() != entry["sha256"]:
        raise CheckpointError(f"{path} is corrupt (sha256 differs from {EXPORT})")
    with np.load(path) as npz:
      arrays.update({k: npz[k] for k in npz.files})
  graphdef, abstract = _abstract_model(config)
  pure = nnx.to_pure_dict(abstract)
  missing = sorted(set(_flat(pure)) - set(arrays))
  if missing:
    raise CheckpointError(f"{folder} lacks weights for {missing[:3]} ({len(missing)} in all)")

  def fill(tree, prefix=""):
    return {k: fill(v, f"{prefix}{k}/") if isinstance(v, dict)
            else jax.numpy.asarray(arrays[f"{prefix}{k}"], v.dtype) for k, v in tree.items()}

  nnx.replace_by_pure_dict(abstract, fill(pure))
  return nnx.merge(graphdef, abstract)
