"""Does MuJoCo C as decompose's engine change its answers? Paired against the JAX engine.

  python experiments/cpu_engine/run.py --model=assets/blocks_model --towers=40 --out=DIR

Fresh towers of a seed never trained on, generated as the model's dataset; the shipped
model decomposes each with its own settings (the paper's inputs) and with
`DecomposeConfig.best()` (depth fit and refinement by differences), once with
`simulator="jax"` (the data's JAX engine, the box-plane step) and once with
`simulator="mujoco"` (MuJoCo's C engine through the host callback, decompose's engine
on a CPU), on the same objects and keys. Densities are paired with the true boxes
bottom to top; per settings: top-1 and RMSE (slots) of each engine, the paired
difference with its 95 % bootstrap interval (objects resampled), and how often the two
engines pick the same slots. Refinement runs the JAX engine whatever `simulator` says
(after this study: through C it lost top-1). Writes DIR/cpu_engine_<settings>.json.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time

import jax
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import OBS_KEYS, density_to_slot
from ppdjax.dataset import generation
from ppdjax.infer.config import DecomposeConfig
from ppdjax.infer.decompose import model_settings
from ppdjax.primitives import bottom_to_top
from ppdjax.report.provenance import write_provenance
from ppdjax.training import checkpoints

flags.DEFINE_string("model", "assets/blocks_model", "The model.")
flags.DEFINE_integer("towers", 40, "Fresh towers (each in the dataset's configurations).")
flags.DEFINE_integer("seed", 90_202, "Their seed (never used for training).")
flags.DEFINE_integer("batch", 64, "Objects per decompose call.")
flags.DEFINE_list("settings", ["model", "best"], "Which: model (its own), best.")
flags.DEFINE_string("out", "experiments/results/cpu_engine", "Output folder.")
FLAGS = flags.FLAGS


def slot_errors(got, truth) -> np.ndarray:
  """(B, K) slot error of each true box (bottom to top; nan where no box or no answer)."""
  got, truth = bottom_to_top(got), bottom_to_top(truth)
  err = (density_to_slot(np.asarray(got.density)) - density_to_slot(np.asarray(truth.density)))
  return np.where(np.asarray(got.valid) & np.asarray(truth.valid), err,
                  np.where(np.asarray(truth.valid), np.inf, np.nan))


def summary(err: np.ndarray) -> tuple[float, float]:
  """(top-1 %, RMSE in slots) over the true boxes (a missing answer counts as wrong)."""
  true = ~np.isnan(err)
  top1 = 100.0 * np.mean(err[true] == 0)
  finite = err[true & np.isfinite(err)]
  return float(top1), float(np.sqrt(np.mean(finite ** 2)))


def paired(a: np.ndarray, b: np.ndarray, towers: np.ndarray) -> dict:
  """b − a for top-1 and RMSE, with 95 % intervals resampling whole towers."""
  diff = lambda i: np.subtract(summary(b[i]), summary(a[i]))
  top1 = metrics.bootstrap_interval(lambda i: diff(i)[0], len(a), groups=towers)
  rmse = metrics.bootstrap_interval(lambda i: diff(i)[1], len(a), groups=towers)
  d = diff(np.arange(len(a)))
  return {"top1_diff": d[0], "top1_diff_95": list(top1), "rmse_diff": d[1],
          "rmse_diff_95": list(rmse)}


def main(argv):
  del argv
  trained = checkpoints.load(FLAGS.model)
  with tempfile.TemporaryDirectory() as folder:
    test = generation.generate_fresh(trained[1], folder, FLAGS.towers, FLAGS.seed)
    data = test.take(np.arange(len(test)), keys=OBS_KEYS + ("depth", "primitives", "tower_id"))
    camera = test.camera
  n = len(data["voxels"])
  out = {"objects": n, "towers": FLAGS.towers, "seed": FLAGS.seed, "model": FLAGS.model,
         "device": jax.devices()[0].device_kind, "cpu_count": os.cpu_count()}
  truth = jax.tree.map(np.asarray, data["primitives"])
  for name, base in (("model", model_settings(trained)), ("best", DecomposeConfig.best())):
    if name not in FLAGS.settings:
      continue
    errs, rows = {}, {}
    for simulator in ("jax", "mujoco"):
      decompose = ppdjax.make_decompose_fn(trained, base.replace(simulator=simulator),
                                           camera=camera)
      keys = OBS_KEYS + (("depth",) if base.fit.depth else ())
      parts, t0 = [], time.perf_counter()
      for start in range(0, n, FLAGS.batch):
        obs = {k: data[k][start:start + FLAGS.batch] for k in keys}
        got = decompose(obs, jax.random.fold_in(jax.random.key(0), start))
        parts.append(jax.device_get(got.primitives))
      seconds = time.perf_counter() - t0
      got = jax.tree.map(lambda *x: np.concatenate(x), *parts)
      errs[simulator] = slot_errors(got, truth)
      top1, rmse = summary(errs[simulator])
      rows[simulator] = {"top1": top1, "rmse": rmse, "seconds_with_compile": seconds,
                         "settings": str(decompose.settings)}
      print(f"{name} {simulator}: top-1 {top1:.1f} %, RMSE {rmse:.2f} ({seconds:.0f} s)",
            flush=True)
    a, b = errs["jax"], errs["mujoco"]
    both = ~np.isnan(a)
    same = float(np.mean((a == b)[both]))
    out[name] = {**rows, "paired_mujoco_minus_jax": paired(a, b, data["tower_id"]),
                 "same_slot_fraction": same,
                 "config": base.to_dict()}
    print(f"{name}: same slot on {100 * same:.1f} % of boxes; "
          f"{out[name]['paired_mujoco_minus_jax']}", flush=True)
  os.makedirs(FLAGS.out, exist_ok=True)
  path = os.path.join(FLAGS.out, f"cpu_engine_{'_'.join(FLAGS.settings)}.json")
  with open(path, "w") as f:
    json.dump(out, f, indent=1, default=float)
  write_provenance(path, command=sys.argv, weights=FLAGS.model, headlines={
      f"{name}: top-1, C − JAX (points)": f"{name}/paired_mujoco_minus_jax/top1_diff"
      for name in FLAGS.settings})


if __name__ == "__main__":
  app.run(main)
