"""Orbax checkpoints of a training run, and `load(workdir)` for inference and notebooks.

A workdir holds `config.json` (the preset the run was made with), `checkpoints/` (the
last few: model and optimizer, for exact resume) and `best/` (the model with the lowest
validation loss).
"""

from __future__ import annotations

import json
import os

import jax
import ml_collections
import orbax.checkpoint as ocp
from flax import nnx

LATEST, BEST = "checkpoints", "best"


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
  """Restores the named nnx States (given as abstract targets) from `step`."""
  args = {k: ocp.args.StandardRestore(nnx.to_pure_dict(v)) for k, v in abstract_states.items()}
  restored = manager.restore(step, args=ocp.args.Composite(**args))
  out = {}
  for k, v in abstract_states.items():
    state = jax.tree.map(lambda x: x, v)
    nnx.replace_by_pure_dict(state, restored[k])
    out[k] = state
  return out


def save_config(workdir: str, config: ml_collections.ConfigDict) -> None:
  os.makedirs(workdir, exist_ok=True)
  with open(os.path.join(workdir, "config.json"), "w") as f:
    f.write(config.to_json_best_effort(indent=1, sort_keys=True))


def read_config(workdir: str) -> ml_collections.ConfigDict:
  path = os.path.join(workdir, "config.json")
  if not os.path.exists(path):
    raise CheckpointError(f"{workdir} is not a training workdir: {path} is missing")
  try:
    with open(path) as f:
      return ml_collections.ConfigDict(_lists_to_tuples(json.load(f)))
  except json.JSONDecodeError as e:
    raise CheckpointError(f"{path} is corrupt: {e}") from e


def _lists_to_tuples(d):
  if isinstance(d, dict):
    return {k: _lists_to_tuples(v) for k, v in d.items()}
  return tuple(d) if isinstance(d, list) else d


def load(workdir: str, which: str = "best"):
  """The trained model of a workdir, in eval mode, and its config.

  Args:
    workdir: a directory written by `python -m ppdjax.train` (or a shipped model: the
      same layout).
    which: "best" (lowest validation loss) or "latest".

  Returns:
    (model, config): a `ppdjax.model.PPD` and the run's ConfigDict.

  Raises:
    CheckpointError naming what is missing.
  """
  from ppdjax.model import PPD

  if which not in (BEST, "latest"):
    raise ValueError(f"which must be 'best' or 'latest', got {which!r}")
  config = read_config(workdir)
  folder = os.path.join(os.path.abspath(workdir), BEST if which == BEST else LATEST)
  if not os.path.isdir(folder):
    raise CheckpointError(f"{workdir} has no checkpoint: {folder} is missing")
  manager = ocp.CheckpointManager(folder, item_names=("model",) if which == BEST else
                                  ("model", "optimizer"),
                                  options=ocp.CheckpointManagerOptions(create=False))
  step = manager.latest_step()
  if step is None:
    raise CheckpointError(f"{workdir} has no checkpoint: {folder} is empty")
  graphdef, abstract = nnx.split(nnx.eval_shape(lambda: PPD(config.model, rngs=nnx.Rngs(0))))
  state = restore(manager, step, model=abstract)["model"]
  model = nnx.merge(graphdef, state)
  manager.close()
  return model, config  # every call site passes train=False unless training
