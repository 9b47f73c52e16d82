"""Shared steps of the reproduction pipelines (`python -m ppdjax.reproduce blocks|tools`).

Each model variant trains into ROOT/<variant> and is evaluated into ROOT/<variant>/eval;
both steps resume or are skipped when already done, so a pipeline can be rerun after an
interruption.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time

import jax
from absl import app, logging

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

from ppdjax.eval import partial
from ppdjax.report.provenance import write_provenance
from ppdjax.reproduce import steps as pipeline_steps
from ppdjax.training import loop  # noqa: E402

# variant -> (its model keys over the preset's, the paper's Table 2 row). The ablations
# turn an encoder off; the RGB-D row reads a depth video of each push instead of its 3D
# trajectory (nn.depth_video).
VARIANTS = {"full": ({}, "PPD (full)"),
            "no_trajectory": ({"use_trajectory": False}, "PPD (no trajectory)"),
            "no_image": ({"use_image": False, "image_weights": ""}, "PPD (no image)"),
            "no_voxels": ({"use_voxels": False}, "PPD (no voxels)"),
            "rgbd": ({"physics_input": "depth_video"}, "PPD (RGB-D)")}


def variant_config(config, variant: str):
  config = config.copy_and_resolve_references()
  for key, value in VARIANTS[variant][0].items():
    config.model[key] = value
  return config


def ensure_trained(config, data_dir: str, root: str, variant: str) -> str:
  """Trains (or resumes, or skips) a variant; returns its workdir."""
  logging.set_verbosity(logging.WARNING)  # orbax logs every save at INFO
  workdir = os.path.join(root, variant)
  t0 = time.perf_counter()
  print(f"[{variant}] training -> {workdir}", flush=True)
  loop.train_and_evaluate(variant_config(config, variant), data_dir, workdir)
  pipeline_steps.log_call(root, f"train {variant}", time.perf_counter() - t0, True)
  return workdir


# The network alone (the ablations' rows, and Table 2's PPD rows): its arg-max, no fit,
# no sampling, no baselines: keys of `schema.EvalConfig` over the preset's eval section.
NETWORK_ONLY = {"samples": 1, "refine": False, "baselines": False, "fit": False,
                "image_fit": False, "depth": False, "face_spread": 0.0,
                "selection_horizon": 0, "screen_steps": 0, "mass_match": False,
                "estimator": "", "joint": False, "true_shapes": False, "table4_objects": 0,
                "network_prior_weight": -1.0}


def eval_command(workdir: str, data: str, settings, **extra) -> str:
  """The `python -m ppdjax.evaluate` command line of an evaluation with the typed eval
  section `settings`: its values as --config.eval overrides, `extra` as flags."""
  values = dataclasses.asdict(settings)
  return (f"python -m ppdjax.evaluate --workdir={workdir} --data={data}"
          + "".join(f" --{k}={v}" for k, v in extra.items() if v not in (None, ""))
          + "".join(f" --config.eval.{k}={v}" for k, v in sorted(values.items())))


def same_settings(results: dict, settings, **extra) -> bool:
  """Whether saved results were made with the typed eval section `settings` (the batch
  size aside: it is padded to the devices) and `extra` (max_objects, subset, split)."""
  want = {k: v for k, v in dataclasses.asdict(settings).items() if k != "batch_size"}
  if not settings.baselines:
    want["table4_objects"] = 0
  want.update(extra)
  return all(json.dumps(results.get(k, partial.UNSET_BEFORE.get(k))) == json.dumps(v)
             for k, v in want.items())


def write(out_dir: str, name: str, payload: dict, markdown: str) -> None:
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, f"{name}.json"), "w") as f:
    json.dump(payload, f, indent=1)
  write_provenance(os.path.join(out_dir, f"{name}.json"), command=payload.get("command", ""))
  with open(os.path.join(out_dir, f"{name}.md"), "w") as f:
    f.write(markdown)
  print(f"wrote {out_dir}/{name}.json and {name}.md", flush=True)


EVALUATION_FILES = ("results.json", "results.md", "confusion.png")


def write_json_atomically(path: str, payload: dict) -> None:
  """`payload` as JSON at `path`, whole or not at all (a record a done-check reads)."""
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    json.dump(payload, f, indent=1)
  os.replace(tmp, path)


def read_evaluation(folder: str) -> dict:
  """The results.json of an evaluation's output folder (`python -m ppdjax.evaluate
  --out=FOLDER`); a usage error naming the folder if it has none."""
  src = os.path.join(folder, "results.json")
  if not os.path.exists(src):
    raise app.UsageError(f"{src} does not exist: --eval names an evaluation's output folder")
  with open(src) as f:
    return json.load(f)


def copy_evaluation(folder: str, out: str) -> None:
  """An evaluation's results.json, results.md and confusion.png, copied into `out`."""
  os.makedirs(out, exist_ok=True)
  for name in EVALUATION_FILES:
    if os.path.exists(os.path.join(folder, name)):
      shutil.copyfile(os.path.join(folder, name), os.path.join(out, name))


def save_logs(pipe, out_dir: str, variants: tuple[str, ...]) -> None:
  """Copies a run's small logs beside its tables: each variant's metrics.jsonl, the
  steps' wall times and the dataset card (those that exist)."""
  os.makedirs(out_dir, exist_ok=True)
  copies = {os.path.join(pipe.workdir(v), "metrics.jsonl"): f"{v}.metrics.jsonl"
            for v in variants}
  copies[os.path.join(pipe.root, "steps.jsonl")] = "steps.jsonl"
  copies[os.path.join(pipe.data, "card.md")] = "data_card.md"
  for src, name in copies.items():
    if os.path.exists(src):
      shutil.copyfile(src, os.path.join(out_dir, name))
