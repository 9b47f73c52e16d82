"""Orbax checkpoints of a training run, and `load(workdir)` for inference and notebooks.

A workdir holds `config.json` (the preset the run was made with, read back through
`configs.schema`), `decompose.json` (its decomposition settings and the camera of its
training data: what `make_decompose_fn(workdir)` runs), `checkpoints/` (the last few:
model and optimizer, for exact resume) and `best/` (the model with the lowest validation
loss). `export` writes a model to ship instead: `config.json`, `decompose.json`,
`export.json` and its weights as `weights-NN.npz` files of bounded size; `load` reads both
layouts. A missing file raises `MissingFileError` (a CheckpointError and a
FileNotFoundError), any other problem `CheckpointError` (a ValueError), naming the file.
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
from ppdjax.dataset.readers import read_json, read_npz
from ppdjax.nn.model import PPD

LATEST, BEST = "checkpoints", "best"
EXPORT = "export.json"
DECOMPOSE_FILE = "decompose.json"


class CheckpointError(ValueError):
  """A workdir without a usable checkpoint or config."""


class MissingFileError(CheckpointError, FileNotFoundError):
  """A workdir, checkpoint or weights file that is not there."""


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
  record = read_json(path, error=CheckpointError, missing=MissingFileError)
  try:
    return {"config": DecomposeConfig.from_dict(record["config"]), "camera": record["camera"]}
  except (KeyError, TypeError, ValueError) as e:
    raise CheckpointError(f"{path} is corrupt: {type(e).__name__}: {e}") from e


def read_config(workdir: str) -> ml_collections.ConfigDict:
  """A run's config.json through the schema: keys it predates take the behaviour they
  had (`schema.complete`); an unknown or ill-typed key is named."""
  if not isinstance(workdir, (str, os.PathLike)):
    raise CheckpointError(f"expected a model folder (a path), got {type(workdir).__name__}")
  path = os.path.join(workdir, "config.json")
  if not os.path.isdir(workdir):
    raise (CheckpointError(f"{workdir} is a file, not a model folder or training workdir")
           if os.path.exists(workdir) else
           MissingFileError(f"{workdir}: no such model folder or training workdir"))
  if not os.path.exists(path):
    raise MissingFileError(f"{workdir} is not a training workdir: {path} is missing")
  saved = _lists_to_tuples(read_json(path, error=CheckpointError, missing=MissingFileError))
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
    workdir: a directory written by `python -m ppdjax.train` (config.json beside best/ and
      checkpoints/), or a model written by `export` (config.json, export.json and
      weights-NN.npz files, such as those shipped in assets/).
    which: "best" (lowest validation loss) or "latest"; an export has one model.

  Returns:
    (model, config): a `ppdjax.nn.model.PPD` and the run's ConfigDict.

  Raises:
    MissingFileError (a CheckpointError and a FileNotFoundError) naming what is missing;
    CheckpointError naming a corrupt file, or the first array whose stored shape is not
    the one config.json's model has (a config.json from another model).
  """
  if which not in (BEST, "latest"):
    raise CheckpointError(f"which must be 'best' or 'latest', got {which!r}")
  config = read_config(workdir)
  if os.path.exists(os.path.join(workdir, EXPORT)):
    return _load_export(workdir, config), config
  folder = os.path.join(os.path.abspath(workdir), BEST if which == BEST else LATEST)
  if not os.path.isdir(folder):
    raise MissingFileError(f"{workdir} has no checkpoint: {folder} is missing")
  names = ("model",) if which == BEST else ("model", "optimizer")
  manager = ocp.CheckpointManager(folder, item_names=names,
                                  item_handlers={n: ocp.StandardCheckpointHandler()
                                                 for n in names},
                                  options=ocp.CheckpointManagerOptions(create=False))
  try:
    step = manager.latest_step()
    if step is None:
      raise CheckpointError(f"{workdir} has no checkpoint: {folder} is empty")
    graphdef, abstract = _abstract_model(config)
    stored = _stored_shapes(manager, step)
    if stored is not None:  # checked first: orbax restores the stored shapes silently
      _check_shapes(abstract, stored, workdir, f"{folder}/{step}")
    state = restore(manager, step, model=abstract)["model"]
  finally:
    manager.close()
  return nnx.merge(graphdef, state), config  # call sites pass train=False unless training


def _stored_shapes(manager, step: int) -> dict | None:
  """{'a/b/0': shape} of a checkpoint's model from its metadata; None where the metadata
  cannot be read (restoring then names the unreadable file)."""
  try:
    leaves = jax.tree_util.tree_leaves_with_path(manager.item_metadata(step)["model"])
  except Exception:  # pylint: disable=broad-except
    return None
  key = lambda k: str(getattr(k, "key", getattr(k, "idx", k)))
  return {"/".join(key(k) for k in path): tuple(leaf.shape) for path, leaf in leaves
          if hasattr(leaf, "shape")} or None


def _check_shapes(abstract, stored: dict, workdir: str, weights: str) -> None:
  """CheckpointError unless the weights in `weights` have exactly the arrays and shapes
  of the model config.json describes: a config.json copied from another model would
  otherwise load arrays of the wrong shape and fail far from here (inside an einsum)."""
  want = {k: tuple(v.shape) for k, v in _flat(nnx.to_pure_dict(abstract)).items()}
  config = os.path.join(workdir, "config.json")
  differ = [k for k in sorted(want) if k in stored and tuple(stored[k]) != want[k]]
  if differ:
    k = differ[0]
    raise CheckpointError(
        f"{config} does not match the weights: array {k} is {tuple(stored[k])} in {weights} "
        f"but {want[k]} in the model config.json describes ({len(differ)} of {len(want)} "
        "arrays differ); use the config.json saved with these weights")
  lacks, extra = sorted(set(want) - set(stored)), sorted(set(stored) - set(want))
  why = ([f"its model has {len(lacks)} arrays the weights lack ({', '.join(lacks[:3])})"]
         if lacks else []) + ([f"the weights hold {len(extra)} arrays its model lacks "
                               f"({', '.join(extra[:3])})"] if extra else [])
  if why:
    raise CheckpointError(f"{config} does not match the weights in {weights}: "
                          f"{'; '.join(why)}; use the config.json saved with these weights")


def _abstract_model(config):
  try:
    return nnx.split(nnx.eval_shape(lambda: PPD(config.model, rngs=nnx.Rngs(0))))
  except (ValueError, TypeError) as e:  # a config whose model cannot be built
    raise CheckpointError(f"config.model describes no model that can be built: {e}") from e


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
  """The model of an export folder: export.json, the files' sums and the shapes checked."""
  path = os.path.join(folder, EXPORT)
  record = read_json(path, error=CheckpointError, missing=MissingFileError)
  entries = record.get("files")
  if not (isinstance(entries, list) and entries and all(
      isinstance(e, dict) and isinstance(e.get("name"), str) and "sha256" in e
      for e in entries)):
    raise CheckpointError(f"{path} is corrupt: 'files' must list the weights files, each "
                          "with its name and sha256")
  arrays = {}
  for entry in entries:
    file = os.path.join(folder, entry["name"])
    if not os.path.exists(file):
      raise MissingFileError(f"{folder}: weights file {entry['name']} is missing")
    with open(file, "rb") as f:
      if hashlib.sha256(f.read()).hexdigest() != entry["sha256"]:
        raise CheckpointError(f"{file} is corrupt (sha256 differs from {EXPORT})")
    arrays.update(read_npz(file, "weights", error=CheckpointError, missing=MissingFileError))
  graphdef, abstract = _abstract_model(config)
  _check_shapes(abstract, {k: v.shape for k, v in arrays.items()}, folder, folder)
  bad = [k for k, v in arrays.items()
         if np.issubdtype(v.dtype, np.floating) and not np.all(np.isfinite(v))]
  if bad:  # a diverged run exported: its model would answer NaN
    raise CheckpointError(f"{folder}: weights {bad[:3]} hold NaN or inf")

  def fill(tree, prefix=""):
    return {k: fill(v, f"{prefix}{k}/") if isinstance(v, dict)
            else jax.numpy.asarray(arrays[f"{prefix}{k}"], v.dtype) for k, v in tree.items()}

  nnx.replace_by_pure_dict(abstract, fill(nnx.to_pure_dict(abstract)))
  return nnx.merge(graphdef, abstract)
