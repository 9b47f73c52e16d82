"""Mass-matched +Sample against the paper's +Sample, on the same candidates and boxes.

`select_densities` (ppdjax/infer/sampling.py) picks the candidate whose simulated pushes
are closest to the observed ones, less τ · log prior. The selection study found that
distance stiff in an object's total mass and soft in its split, so on the slot grid the
pick is the candidate with the best total (`results/selection_study/README.md`). With
`mass_match`, every candidate is scaled to the closest one's total mass and simulated
again, and the pick compares splits. This script scores the same candidates on the same
fitted boxes both ways, at several τ (what `make_decompose_fn(..., mass_match=)` does,
one jitted call for all), and scores the densities against the truth (the k-th box from the bottom against
the k-th true box; slots ranked by distance to the answer's continuous density, so top-1
is the nearest slot).

    python experiments/mass_match_study.py --data=DIR --split=val --out=DIR

Writes results.json and results.md under --out.
"""

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import nnx
from tqdm.auto import tqdm

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS, density_to_slot_jax
from ppdjax.infer import baselines, rows, sampling
from ppdjax.infer.batches import evaluation_objects
from ppdjax.sim.rollout_mjx import settings_for

_WORKDIR = flags.DEFINE_string("workdir", "assets/blocks_model", "Trained model.")
_DATA = flags.DEFINE_string("data", None, "Dataset folder (with depth images).", required=True)
_SPLIT = flags.DEFINE_string("split", "val", "Split to score (choose on val).")
_OBJECTS = flags.DEFINE_integer("objects", 0, "Objects spread over the split (0: all).")
_SAMPLES = flags.DEFINE_integer("samples", 512, "Density candidates per object.")
_TAUS = flags.DEFINE_list("taus", ["0", "0.01", "0.02", "0.05", "0.1"], "Prior weights τ (m per nat) to compare.")
_BATCH = flags.DEFINE_integer("batch", 16, "Objects per jitted call.")
_SEED = flags.DEFINE_integer("seed", 0, "Sampling seed.")
_OUT = flags.DEFINE_string("out", None, "Output folder.", required=True)
_FIT = flags.DEFINE_enum("fit", "depth", ["depth", "image"], "Boxes fitted to the voxels and "
                         "then the depth image (ours) or the RGB image (the paper's inputs).")

VARIANTS = ("paper", "mass_match")
SEEN = {"depth": "depth", "image": "RGB"}  # --fit: the image the boxes are fitted to


def make_candidates_fn(model, camera, samples: int, pushes, settings, fit: str = "depth"):
  """One jitted call per batch: decode, fit the boxes (voxels, then `fit`: the depth or the
  RGB image), draw the
  candidates, simulate them (the paper's pass) and again scaled to the closest one's
  total mass (`sampling.match_closest_mass`, the mass-matched pass)."""
  graphdef, state = nnx.split(model)

  @jax.jit
  def run(state, obs, key):
    prims, raw = nnx.merge(graphdef, state).decode(obs)
    logits = raw.density_logits[:, :prims.num_slots, :NUM_DENSITY_SLOTS]
    seen = {"depth": obs["depth"]} if fit == "depth" else {"image": obs["image"]}
    prims = ppdjax.fit_boxes(obs["voxels"], init=prims, camera=camera, **seen)
    traj = obs["trajectories"].astype(jnp.float32)

    def one(p, lg, o, k):
      slots, _ = sampling.candidate_slots(lg, p.valid, samples, k)
      cands = sampling.with_slots(p, slots)
      out = {}
      for name in VARIANTS:
        if name == "mass_match":
          cands = sampling.match_closest_mass(cands, out["paper"]["dist"])
        dist, mae = sampling.score_candidates(cands, o, pushes, settings)
        out[name] = {"dist": dist, "mae": mae, "density": cands.density,
                     "logp": sampling.log_prior(lg, density_to_slot_jax(cands.density),
                                                p.valid)}
      return out
    return jax.vmap(one)(prims, logits, traj, jax.random.split(key, traj.shape[0]))
  return lambda obs, key: jax.device_get(run(state, obs, key))


def score(cands: dict, tau: float, slot, valid, boxes) -> dict:
  """Per-object density counts and trajectory MAE of the pick at τ."""
  pick = np.argmin(sampling.selection_objective(cands["dist"], cands["logp"], tau), -1)
  density = np.take_along_axis(cands["density"], pick[:, None, None], 1)[:, 0]
  ranking = rows.refine_scores(np.zeros(density.shape + (100,)), density, valid)
  out = rows.row_counts(ranking, slot, valid)
  out["mae"] = np.take_along_axis(cands["mae"], pick[:, None], 1)[:, 0]
  out["boxes"] = boxes
  return out


def summary(rec: dict) -> dict:
  """Top-k, RMSE (slots) and MAE (mm) with 95 % bootstrap intervals over objects."""
  n = len(rec["count"])

  def stat(key):
    if key == "mae":
      return lambda i: float(rec["mae"][i].mean())
    if key == "rmse":
      return lambda i: float(np.sqrt(rec["sq_err"][i].sum() / max(rec["count"][i].sum(), 1)))
    return lambda i: 100.0 * rec[key][i].sum() / max(rec["count"][i].sum(), 1)

  out = {"objects": n}
  for key in ("top1", "top5", "top10", "rmse", "mae"):
    out[key] = stat(key)(np.arange(n))
    out[key + "_ci"] = metrics.bootstrap_interval(stat(key), n)
  out["rmse_by_boxes"] = {
      int(b): float(np.sqrt(rec["sq_err"][rec["boxes"] == b].sum()
                            / max(rec["count"][rec["boxes"] == b].sum(), 1)))
      for b in np.unique(rec["boxes"])}
  return out


def to_md(results: dict) -> str:
  lines = [
      "# Mass-matched +Sample against the paper's +Sample",
      "", "```", results["command"], "```", "",
      f"Model `{results['workdir']}`, data `{results['data']}` ({results['split']} split, "
      f"{results['objects']} objects), {results['samples']} candidates on boxes fitted to "
      f"the voxels and the {SEEN[results.get('fit', 'depth')]} image; {results['device']}, "
      f"{results['seconds']:.0f} s. "
      "Top-k in %, RMSE in slots, trajectory MAE in mm; 95 % bootstrap intervals.", "",
      "| selection | τ | top-1 | top-5 | top-10 | RMSE | MAE (mm) | RMSE by boxes |",
      "|---|--:|--:|--:|--:|--:|--:|---|"]
  for name, row in results["rows"].items():
    variant, tau = name.rsplit("@", 1)
    ci = lambda k, d=1: f"{row[k]:.{d}f} [{row[k + '_ci'][0]:.{d}f}, {row[k + '_ci'][1]:.{d}f}]"
    by = " / ".join(f"{b}: {v:.1f}" for b, v in row["rmse_by_boxes"].items())
    lines.append(f"| {variant} | {tau} | {ci('top1')} | {row['top5']:.1f} | "
                 f"{row['top10']:.1f} | {ci('rmse', 2)} | {ci('mae')} | {by} |")
  return "\n".join(lines) + "\n"


def main(_):
  t0 = time.perf_counter()
  data = ppdjax.open_dataset(_DATA.value, _SPLIT.value)
  objects = evaluation_objects(len(data), _OBJECTS.value, "spread")
  model, _ = ppdjax.load(_WORKDIR.value)
  taus = [float(t) for t in _TAUS.value]
  run = make_candidates_fn(model, data.camera, _SAMPLES.value, data.pushes,
                           settings_for(data.engine), _FIT.value)
  records = {f"{v}@{t:g}": [] for v in VARIANTS for t in taus}
  keys = ("voxels", "image", "trajectories", "depth", "primitives")
  b = _BATCH.value
  key = jax.random.key(_SEED.value)
  for start in tqdm(range(0, len(objects), b), desc="batches"):
    idx = objects[start:start + b]
    batch = data.take(np.pad(idx, (0, b - len(idx)), mode="edge"), keys=keys)
    cands = run({k: jnp.asarray(batch[k]) for k in keys[:-1]}, jax.random.fold_in(key, start))
    slot = baselines.true_slots(batch["primitives"])
    boxes = np.asarray(batch["primitives"].valid).sum(-1)
    for name in records:
      variant, tau = name.rsplit("@", 1)
      rec = score(cands[variant], float(tau), slot, slot >= 0, boxes)
      records[name].append({k: v[:len(idx)] for k, v in rec.items()})
  results = {
      "command": "python " + " ".join(sys.argv), "workdir": _WORKDIR.value,
      "data": _DATA.value, "split": _SPLIT.value, "objects": int(len(objects)),
      "samples": _SAMPLES.value, "fit": _FIT.value, "device": jax.devices()[0].device_kind,
      "seconds": time.perf_counter() - t0,
      "rows": {name: summary({k: np.concatenate([r[k] for r in recs]) for k in recs[0]})
               for name, recs in records.items()}}
  os.makedirs(_OUT.value, exist_ok=True)
  with open(os.path.join(_OUT.value, "results.json"), "w") as f:
    json.dump(results, f, indent=1)
  md = to_md(results)
  with open(os.path.join(_OUT.value, "results.md"), "w") as f:
    f.write(md)
  print(md)


if __name__ == "__main__":
  app.run(main)
