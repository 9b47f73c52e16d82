"""τ (+Sample's prior weight) and +Refine's MAP weight, swept together on one split.

  python experiments/prior_study.py --workdir=assets/blocks_model --data=DATA --split=val \
      --out=experiments/results/prior_study_val

Per batch the evaluation's own calls (`evaluator.Evaluator`, no baselines) sample once on
the boxes fitted to voxels and depth and on the true boxes (the oracle column). For every
τ in --taus, each group's best sample (distance − τ·log prior, `sampling.
selection_objective`) is refined by Levenberg–Marquardt under every MAP weight in
--map_weights (`refine.refine_batch`; weight 0 is the plain least-squares fit, the
others share one compiled call). Each cell is scored as the evaluation scores its rows
(top-k, RMSE in slots with 95 % bootstrap intervals, trajectory MAE, RMSE by block count).
Writes OUT.json and OUT.md; "chosen" is the cell of the depth-fitted boxes with the lowest
+Refine RMSE (the rule is fixed before the sweep: choose on validation, report on test).
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from tqdm.auto import tqdm

from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import storage
from ppdjax.infer import baselines, batches, evaluator, rows, sampling, tables
from ppdjax.infer.refine import refine_batch
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS
from ppdjax.training import checkpoints

_WORKDIR = flags.DEFINE_string("workdir", "assets/blocks_model", "The trained model.")
_DATA = flags.DEFINE_string("data", None, "Dataset folder.", required=True)
_SPLIT = flags.DEFINE_string("split", "val", "Split to sweep on (choose on val).")
_MAX = flags.DEFINE_integer("max_objects", 0, "Objects spread over the split (0: all).")
_SAMPLES = flags.DEFINE_integer("samples", 512, "Density samples per object.")
_BATCH = flags.DEFINE_integer("batch_size", 64, "Objects per call.")
_TAUS = flags.DEFINE_list("taus", ["0", "0.02", "0.05", "0.2"], "+Sample prior weights.")
_WEIGHTS = flags.DEFINE_list("map_weights", ["0", "1e-6", "1e-5", "1e-4"],
                             "+Refine MAP weights.")
_OUT = flags.DEFINE_string("out", "experiments/results/prior_study", "OUT.json / OUT.md.")
GROUPS = ("fit_depth", "true")
NAMES = {"fit_depth": "+Fit(depth)", "true": "+True boxes"}


def _stack(trees):
  return jax.tree.map(lambda *x: jnp.concatenate([jnp.asarray(a) for a in x]), *trees)


def _cell(counts: dict, mae, blocks) -> dict:
  idx = np.arange(len(mae))
  out = {**tables.np_metrics(counts, idx), "mae_mm": float(np.mean(mae)),
         "ci95": tables.intervals(counts, mae, resamples=500)}
  out["rmse_by_blocks"] = {str(b): tables.np_metrics(counts, idx[blocks == b])["rmse"]
                           for b in np.unique(blocks)}
  return out


def main(argv):
  del argv
  t0 = time.perf_counter()
  model, config = checkpoints.load(_WORKDIR.value)
  data = storage.open_dataset(_DATA.value, _SPLIT.value)
  objects = batches.evaluation_objects(len(data), _MAX.value, "spread")
  taus = [float(t) for t in _TAUS.value]
  weights = [float(w) for w in _WEIGHTS.value]
  if any(w < 0 for w in weights) or any(t < 0 for t in taus):
    raise ValueError(f"weights must be >= 0, got taus {taus}, map_weights {weights}")
  map_weights = [w for w in weights if w > 0]
  ev = evaluator.Evaluator(model, config, samples=_SAMPLES.value, refine=False,
                            baselines_on=False, depth=True, camera=data.camera,
                            true_shapes=True)
  common = dict(steps=12, pushes=default_pushes(), settings=DEFAULT_SETTINGS)
  plain = jax.jit(functools.partial(refine_batch, prior_weight=0.0, **common))
  map_step = jax.jit(functools.partial(refine_batch, **common))
  records = {}  # (group, tau, weight or None for +Sample) -> list of (counts, mae)
  blocks = []
  batch_size = min(_BATCH.value, len(objects))
  bar = tqdm(total=len(objects), desc="prior study", unit="object")
  for start in range(0, len(objects), batch_size):
    idx = objects[start:start + batch_size]
    keep = len(idx)
    batch = data.take(np.pad(idx, (0, batch_size - keep), mode="edge"),
                      keys=OBS_KEYS + ("primitives", "depth"))
    slot = baselines.true_slots(batch["primitives"])
    valid = slot >= 0
    blocks.append(valid.sum(-1)[:keep])
    out = ev.batch(batch, None, jax.random.key(start))
    starts, cells = [], []
    for g in GROUPS:
      fvalid = np.asarray(out["fitted"][g].valid)
      glogits = out["group_logits"][g].astype(np.float64)
      d, m = out["dist"][:, ev.layout[g]], out["mae"][:, ev.layout[g]]
      for tau in taus:
        obj = sampling.selection_objective(d, out["fit_logp"][g], tau)
        best = np.argmin(obj, -1)
        scores = rows.sample_scores(glogits, out["fit_slots"][g], obj, fvalid)
        records.setdefault((g, tau, None), []).append(
            (rows.row_counts(scores, slot, valid), m[np.arange(batch_size), best]))
        starts.append(ev._best_sample(out, out, g, tau))
        cells.append((g, tau, fvalid))
    prims, prior, d0, m0 = (_stack([s[i] for s in starts]) for i in range(4))
    traj = jnp.tile(jnp.asarray(batch["trajectories"]), (len(starts),) + (1,) * 3)
    results = {}
    if 0.0 in weights:
      results[0.0] = jax.device_get(plain(prims, prior, traj, d0, m0))
    if map_weights:
      n = len(map_weights)
      rep = lambda x: jnp.concatenate([x] * n)
      w = jnp.repeat(jnp.asarray(map_weights, jnp.float32), len(d0))
      res = jax.device_get(map_step(jax.tree.map(rep, prims), rep(prior),
                                    rep(traj), rep(d0), rep(m0), prior_weight=w))
      for j, wt in enumerate(map_weights):
        results[wt] = jax.tree.map(lambda x, j=j: x[j * len(d0):(j + 1) * len(d0)], res)
    for wt, res in results.items():
      for c, (g, tau, fvalid) in enumerate(cells):
        part = slice(c * batch_size, (c + 1) * batch_size)
        scores = rows.refine_scores(out["group_logits"][g].astype(np.float64),
                                    res["density"][part], fvalid)
        records.setdefault((g, tau, wt), []).append(
            (rows.row_counts(scores, slot, valid), res["mae"][part]))
    for key in records:  # drop the padding
      c, m = records[key][-1]
      records[key][-1] = ({k: v[:keep] for k, v in c.items()}, m[:keep])
    bar.update(keep)
  bar.close()
  blocks = np.concatenate(blocks)
  table = []
  for (g, tau, wt), parts in records.items():
    counts = {k: np.concatenate([p[0][k] for p in parts]) for k in parts[0][0]}
    mae = np.concatenate([p[1] for p in parts])
    table.append({"group": g, "tau": tau, "map_weight": wt, **_cell(counts, mae, blocks)})
  refined = [r for r in table if r["group"] == "fit_depth" and r["map_weight"] is not None]
  chosen = min(refined, key=lambda r: (r["rmse"], -r["top1"]))
  result = {"command": " ".join(["python"] + sys.argv), "workdir": _WORKDIR.value,
            "data": _DATA.value, "split": _SPLIT.value, "objects": int(len(objects)),
            "samples": _SAMPLES.value, "chosen": {"tau": chosen["tau"],
                                                  "map_weight": chosen["map_weight"]},
            "seconds": round(time.perf_counter() - t0, 1), "cells": table}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value + ".json", "w") as f:
    json.dump(result, f, indent=1)
  with open(_OUT.value + ".md", "w") as f:
    f.write(_markdown(result))
  print(_markdown(result))


def _markdown(result: dict) -> str:
  lines = [f"# τ and the MAP weight on the {result['split']} split ({result['objects']} "
           f"objects, {result['samples']} samples)", "", "```", result["command"], "```", "",
           "| boxes | τ | MAP weight | top-1 | top-5 | top-10 | RMSE | MAE (mm) | "
           "RMSE by blocks |", "|---|--:|--:|--:|--:|--:|--:|--:|---|"]
  for r in sorted(result["cells"], key=lambda r: (r["group"], r["map_weight"] is not None,
                                                  r["map_weight"] or 0, r["tau"])):
    ci = r["ci95"]
    weight = "+Sample" if r["map_weight"] is None else f"{r['map_weight']:g}"
    by = " / ".join(f"{v:.1f}" for v in r["rmse_by_blocks"].values())
    lines.append(
        f"| {NAMES[r['group']]} | {r['tau']:g} | {weight} | {r['top1']:.1f} "
        f"[{ci['top1'][0]:.1f}, {ci['top1'][1]:.1f}] | {r['top5']:.1f} | {r['top10']:.1f} "
        f"| {r['rmse']:.2f} [{ci['rmse'][0]:.2f}, {ci['rmse'][1]:.2f}] | {r['mae_mm']:.1f} "
        f"| {by} |")
  c = result["chosen"]
  lines += ["", f"Chosen (lowest +Fit(depth)+Refine RMSE): τ = {c['tau']:g}, MAP weight = "
            f"{c['map_weight']:g}. {result['seconds']:.0f} s.", ""]
  return "\n".join(lines)


if __name__ == "__main__":
  app.run(main)
