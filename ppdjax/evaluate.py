"""Evaluation on a dataset split: paper Tables 2, 4 and 5 for one trained model.

  python -m ppdjax.evaluate --workdir=out/run --data=out/blocks_tiny [--samples=512]
      [--refine] [--out=DIR]

Per batch, one jitted call decodes the objects and simulates, per object, in one batched
MJX call: the network's S density samples (candidate 0 its arg-max), Table 4's sampling
baselines (S uniform densities on the true shape; S random tower shapes with uniform
densities) and Table 2's baselines' guesses on the true shape. With --refine, a second
jitted call fits the best sample's densities by Levenberg–Marquardt through MJX.

Rows (density metrics over true boxes, the k-th decoded box against the k-th true box
from the bottom; `docs/inference.md` says how +Sample and +Refine rank slots):
  PPD             the network's per-box slot scores;
  PPD+Sample      slots ranked by the best selection objective of a sample that has them
                  (trajectory distance − prior_weight · log prior; the paper: distance);
  PPD+Sample+Refine  slots ranked by closeness to the refined continuous density;
  Frequent, Nearest, Oracle (`ppdjax.baselines`), on the true shape.
MAE is the paper's trajectory MAE in mm (`metrics.trajectory_mae`).
"""

from __future__ import annotations

import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from tqdm.auto import tqdm

from ppdjax import baselines, checkpoints, data, inference, metrics
from ppdjax.materials import NUM_DENSITY_SLOTS, SLOT_DENSITY
from ppdjax.physics import default_pushes
from ppdjax.primitives import Primitives
from ppdjax.rollout_mjx import DEFAULT_SETTINGS, rollout_object

OBS_KEYS = ("voxels", "image", "trajectories")
PREFIXES = (1, 8, 64, 512)  # Table 4's sample counts
BASELINES = ("Frequent", "Nearest", "Oracle")
PPD_ROWS = ("PPD", "PPD+Sample", "PPD+Sample+Refine")
PRIOR_WEIGHTS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)  # τ swept for +Sample (m/nat)


def simultaneous_candidates() -> int:
  """Candidates simulated at once (objects × candidates; × 4 pushes in rollouts): 16,384
  on an accelerator (65,536 rollouts run at ~10× the rate of 2,048, benchmarks.md), 2,048
  on a CPU."""
  return 2048 if jax.default_backend() == "cpu" else 16384


def _take_bt(prims: Primitives) -> Primitives:
  """Ground truth reordered bottom to top (the order baselines and targets use)."""
  order = baselines.bottom_to_top_order(prims)
  return jax.tree.map(lambda x: np.take_along_axis(
      np.asarray(x), order.reshape(order.shape + (1,) * (np.ndim(x) - 2)), 1), prims)


def _decode(graphdef, state, obs, true):
  model = nnx.merge(graphdef, state)
  pred, raw = model.decode(obs)
  logits = raw.density_logits[:, :pred.num_slots, :NUM_DENSITY_SLOTS]
  return pred, logits, metrics.shape_counts(pred, true)


def _simulate(pred, logits, true, base_slots, pool, obs_traj, key, *, samples, with_baselines,
              chunk, pushes, settings):
  """Per object: (distance, MAE) of every candidate, and the network's candidate slots."""
  b, k = pred.density.shape
  keys = jax.random.split(key, (b, 3))

  def one(args):
    p, lg, t, bs, traj, kk = args
    slots, _ = inference.candidate_slots(lg, p.valid, samples, kk[0])
    cands = [inference.with_slots(p, slots)]
    if with_baselines:
      uniform, _ = inference.candidate_slots(jnp.zeros_like(lg), t.valid, samples, kk[1],
                                             include_mode=False)
      shape_slots = jax.random.randint(kk[2], (samples, k), 0, NUM_DENSITY_SLOTS)
      cands += [inference.with_slots(t, uniform),
                pool.replace(density=(shape_slots + 1.0) * SLOT_DENSITY),
                inference.with_slots(t, bs)]
    cands = jax.tree.map(lambda *x: jnp.concatenate(x), *cands)
    dist, mae = inference.score_candidates(cands, traj, pushes, settings)
    return dist, mae, slots

  return jax.lax.map(one, (pred, logits, true, base_slots, obs_traj, keys), batch_size=chunk)


def _refine(prims, obs_traj, sample_dist, sample_mae, *, steps, pushes, settings):
  """Refined densities, kept where they also lower the trajectory distance (as `decompose`)."""
  def one(p, traj, d0, m0):
    out, info = inference.refine_densities(p, traj, pushes, steps=steps, settings=settings)
    sim = rollout_object(out, pushes, steps=traj.shape[-2], settings=settings)
    d1 = metrics.trajectory_distance(sim, traj)
    better = d1 < d0
    return (jnp.where(better, out.density, p.density), info["cost_start"], info["cost"],
            jnp.minimum(d1, d0), jnp.where(better, metrics.trajectory_mae(sim, traj), m0))
  return jax.vmap(one)(prims, obs_traj, sample_dist, sample_mae)


def sample_scores(logits, slots, dist, valid):
  """(B, K, 100) +Sample ranking: slots a sample has, by that sample's best distance first.

  Slots no sample has follow in the network's order; boxes the network did not emit keep
  the network's scores.
  """
  b, s, k = slots.shape
  best = np.full((b, k, NUM_DENSITY_SLOTS), np.inf)
  bi, _, ki = np.meshgrid(np.arange(b), np.arange(s), np.arange(k), indexing="ij")
  np.minimum.at(best, (bi, ki, slots), np.broadcast_to(dist[:, :, None], slots.shape))
  lsm = np.asarray(jax.nn.log_softmax(jnp.asarray(logits, jnp.float32)), np.float64)
  out = np.where(np.isfinite(best), 1e6 - np.where(np.isfinite(best), best, 0.0), lsm - 1e6)
  return np.where(valid[..., None], out, logits)


def refine_scores(logits, density, valid):
  """(B, K, 100) +Refine ranking: slots by distance to the refined (continuous) slot."""
  cont = density / SLOT_DENSITY - 1.0
  out = -np.abs(cont[..., None] - np.arange(NUM_DENSITY_SLOTS))
  return np.where(valid[..., None], out, logits)


class Evaluator:
  """Compiles the per-batch calls once for a model, batch size and sample count."""

  def __init__(self, model, config, *, samples: int, refine: bool, refine_steps: int = 12,
               baselines_on: bool = True, prior_weight: float = 0.0, pushes=None,
               settings=DEFAULT_SETTINGS):
    if samples < 1:
      raise ValueError(f"samples must be >= 1, got {samples}")
    self.config, self.samples, self.refine = config, samples, refine
    self.baselines_on, self.prior_weight = baselines_on, prior_weight
    pushes = default_pushes() if pushes is None else pushes
    per_object = samples * (3 if baselines_on else 1) + (3 if baselines_on else 0)
    chunk = max(1, simultaneous_candidates() // per_object)
    self.graphdef, self.state = nnx.split(model)
    self._decode = jax.jit(functools.partial(_decode, self.graphdef))
    self._simulate = jax.jit(functools.partial(
        _simulate, samples=samples, with_baselines=baselines_on, chunk=chunk, pushes=pushes,
        settings=settings))
    self._refine = jax.jit(functools.partial(
        _refine, steps=refine_steps, pushes=pushes, settings=settings))

  def batch(self, batch: dict, base_scores: np.ndarray | None, key) -> dict:
    """Per-object arrays for one batch (see `evaluate` for what they become)."""
    obs = {k: jnp.asarray(batch[k]) for k in OBS_KEYS}
    true = _take_bt(batch["primitives"])
    pred, logits, shape = self._decode(self.state, obs, jax.tree.map(jnp.asarray, true))
    b, k = true.density.shape
    base_slots = (np.argmax(base_scores, -1).astype(np.int32) if base_scores is not None
                  else np.zeros((b, len(BASELINES), k), np.int32))
    pool = baselines.random_shapes(int(jax.random.randint(key, (), 0, 2**31 - 1)),
                                   self.samples, num_slots=k)
    dist, mae, slots = self._simulate(pred, logits, true, jnp.asarray(base_slots),
                                      jax.tree.map(jnp.asarray, pool), obs["trajectories"],
                                      key)
    out = jax.device_get({"pred": pred, "logits": logits, "shape": shape, "dist": dist,
                          "mae": mae, "slots": slots})
    if self.refine:
      logp = jax.vmap(inference.log_prior)(logits, jnp.asarray(out["slots"]), pred.valid)
      best = np.argmin(out["dist"][:, :self.samples] - self.prior_weight * np.asarray(logp), -1)
      start = np.take_along_axis(out["slots"], best[:, None, None], 1)[:, 0]
      prims = pred.replace(density=jnp.asarray((start + 1.0) * SLOT_DENSITY))
      rows = np.arange(len(best))
      density, c0, c1, rdist, rmae = jax.device_get(self._refine(
          prims, obs["trajectories"], out["dist"][rows, best], out["mae"][rows, best]))
      out["refine"] = {"density": density, "cost_start": c0, "cost": c1, "dist": rdist,
                       "mae": rmae}
    return out


def _row_counts(scores, slot, valid):
  c = metrics.density_counts(jnp.asarray(scores, jnp.float32), jnp.asarray(np.maximum(slot, 0)),
                             jnp.asarray(valid))
  return {n: np.asarray(v) for n, v in c.items()}


def evaluation_objects(total: int, max_objects: int = 0, subset: str = "first") -> np.ndarray:
  """Indices of the objects to evaluate: all, the first N, or N spread evenly ("spread")."""
  if subset not in ("first", "spread"):
    raise ValueError(f"subset must be 'first' or 'spread', got {subset!r}")
  if max_objects < 0:
    raise ValueError(f"max_objects must be >= 0, got {max_objects}")
  n = total if not max_objects else min(max_objects, total)
  if subset == "first" or n == total:
    return np.arange(n)
  return np.unique(np.linspace(0, total - 1, n).round().astype(np.int64))


def evaluate(trained, data_dir: str, *, split: str = "test", samples: int = 512,
             refine: bool = False, refine_steps: int = 12, batch_size: int = 16,
             max_objects: int = 0, with_baselines: bool = True, seed: int = 0,
             prior_weight: float = 0.0, subset: str = "first", progress: bool = True) -> dict:
  """Evaluates a trained model (a workdir or (model, config)); returns the results dict.

  +Sample selects by distance − prior_weight · log p (`inference.select_densities`);
  `results["prior_sweep"]` also scores the selection for every τ in PRIOR_WEIGHTS (free:
  the candidates are simulated once). Choose τ on the validation split. With
  `max_objects`, `subset` picks the first N objects ("first") or N spread evenly over the
  split ("spread": many towers, since a tower's 8 configurations are stored together).

  Raises:
    CheckpointError for a workdir without a checkpoint, DatasetError for a dataset
    without the split.
  """
  t_start = time.perf_counter()
  model, config = checkpoints.load(trained) if isinstance(trained, str) else trained
  test = data.open_dataset(data_dir, split)
  objects = evaluation_objects(len(test), max_objects, subset)
  n = len(objects)
  batch_size = max(1, min(batch_size, n))
  train = baselines.TrainingSet(data.open_dataset(data_dir, "train"),
                                progress=progress) if with_baselines else None
  ev = Evaluator(model, config, samples=samples, refine=refine, refine_steps=refine_steps,
                 baselines_on=with_baselines, prior_weight=prior_weight)
  rows = {}
  per_object = {"num_blocks": [], "matched": [], "predicted": [], "true": []}
  confusion = {r: np.zeros((NUM_DENSITY_SLOTS,) * 2, np.int64) for r in PPD_ROWS}
  mae = {}  # row -> list of per-object MAE
  prefix_mae = {}  # (method, N) -> list
  refine_log = {"cost_start": [], "cost": [], "sample_dist": [], "dist": []}
  sweep = {}  # prior weight -> per-batch counts of +Sample
  key = jax.random.key(seed)
  s = samples
  prefixes = sorted({p for p in PREFIXES if p <= s} | {s})
  bar = tqdm(total=n, desc="evaluating", unit="object", disable=not progress)
  for start in range(0, n, batch_size):
    idx = objects[start:start + batch_size]
    keep = len(idx)
    idx = np.pad(idx, (0, batch_size - keep), mode="edge")  # one compiled shape
    batch = test.take(idx, keys=OBS_KEYS + ("primitives", "materials"))
    slot = baselines.true_slots(batch["primitives"])
    valid = slot >= 0
    base = None
    if with_baselines:
      nb = valid.sum(-1)
      base = np.stack([baselines.frequent_scores(train, batch_size, slot.shape[1]),
                       baselines.nearest_scores(train, batch["trajectories"], nb),
                       baselines.oracle_scores(train, batch["materials"], batch["primitives"],
                                               seed * 1_000_003 + start)], 1)
    out = ev.batch(batch, base, jax.random.fold_in(key, start))
    cut = lambda x: x[:keep]
    slot, valid = cut(slot), cut(valid)
    pvalid = cut(np.asarray(out["pred"].valid))
    logits = cut(out["logits"]).astype(np.float64)
    dist, omae, slots = cut(out["dist"]), cut(out["mae"]), cut(out["slots"])
    logp = np.asarray(jax.vmap(inference.log_prior)(jnp.asarray(logits, jnp.float32),
                                                     jnp.asarray(slots), jnp.asarray(pvalid)))
    objective = lambda tau: dist[:, :s] - tau * logp
    best = np.argmin(objective(prior_weight), -1)
    scores = {"PPD": logits,
              "PPD+Sample": sample_scores(logits, slots, objective(prior_weight), pvalid)}
    for tau in PRIOR_WEIGHTS:
      pick = np.argmin(objective(tau), -1)
      c = _row_counts(sample_scores(logits, slots, objective(tau), pvalid), slot, valid)
      c["mae"] = omae[np.arange(keep), pick]
      sweep.setdefault(tau, []).append(c)
    mae.setdefault("PPD", []).append(omae[:, 0])
    mae.setdefault("PPD+Sample", []).append(omae[np.arange(keep), best])
    for p in prefixes:
      pick = np.argmin(dist[:, :p], -1)
      prefix_mae.setdefault(("PPD", p), []).append(omae[np.arange(keep), pick])
    if with_baselines:
      for j, name in enumerate(BASELINES):
        scores[name] = cut(base[:, j])
        mae.setdefault(name, []).append(omae[:, 3 * s + j])
      for m, name in ((1, "Sample Phys."), (2, "Sample Phys.+Shape")):
        d, e = dist[:, m * s:(m + 1) * s], omae[:, m * s:(m + 1) * s]
        for p in prefixes:
          prefix_mae.setdefault((name, p), []).append(
              e[np.arange(keep), np.argmin(d[:, :p], -1)])
    if refine:
      r = jax.tree.map(cut, out["refine"])
      scores["PPD+Sample+Refine"] = refine_scores(logits, r["density"], pvalid)
      mae.setdefault("PPD+Sample+Refine", []).append(r["mae"])
      for name in ("cost_start", "cost", "dist"):
        refine_log[name].append(r[name])
      refine_log["sample_dist"].append(dist[np.arange(keep), best])
    for name, sc in scores.items():
      c = _row_counts(sc, slot, valid)
      rows.setdefault(name, []).append(c)
      if name in confusion:
        guess = np.argmax(sc, -1)
        np.add.at(confusion[name], (slot[valid], guess[valid]), 1)
    per_object["num_blocks"].append(valid.sum(-1))
    for name in ("matched", "predicted", "true"):
      per_object[name].append(cut(np.asarray(out["shape"][name])))
    bar.update(keep)
  bar.close()
  cat = lambda xs: np.concatenate(xs)
  nb = cat(per_object["num_blocks"])
  results = {
      "workdir": trained if isinstance(trained, str) else None, "data": data_dir,
      "split": split, "objects": int(n), "samples": s, "refine": refine,
      "refine_steps": refine_steps if refine else 0, "baselines": with_baselines,
      "model": {"use_voxels": bool(config.model.use_voxels),
                "use_image": bool(config.model.use_image),
                "use_trajectory": bool(config.model.use_trajectory)},
      "f1": metrics.f1_from_counts(*[cat(per_object[k]) for k in ("matched", "predicted",
                                                                   "true")]),
      "table2": {}, "table4": {}, "table5": {}, "mae_units": "mm",
  }
  for name in [r for r in BASELINES + PPD_ROWS if r in rows]:
    parts = rows[name]
    counts = {k: cat([p[k] for p in parts]) for k in parts[0]}
    row = metrics.summarize(counts)
    row["mae"] = float(np.mean(cat(mae[name])))
    results["table2"][name] = row
    results["table5"][name] = {
        str(b): metrics.summarize({k: v[nb == b] for k, v in counts.items()})["rmse"]
        for b in range(2, nb.max() + 1) if np.any(nb == b)}
    results["table5"][name]["overall"] = row["rmse"]
  results["prior_weight"], results["subset"] = prior_weight, subset
  results["prior_sweep"] = {}
  for tau, parts in sweep.items():
    counts = {k: cat([p[k] for p in parts]) for k in parts[0] if k != "mae"}
    results["prior_sweep"][str(tau)] = {**metrics.summarize(counts),
                                        "mae": float(np.mean(cat([p["mae"] for p in parts])))}
  for (name, p), parts in prefix_mae.items():
    results["table4"].setdefault(name, {})[str(p)] = float(np.mean(cat(parts)))
  if refine:
    c0, c1 = cat(refine_log["cost_start"]), cat(refine_log["cost"])
    d0, d1 = cat(refine_log["sample_dist"]), cat(refine_log["dist"])
    results["refine_stats"] = {
        "improved_fraction": float(np.mean(d1 < d0 - 1e-9)),
        "median_distance_ratio": float(np.median(d1 / np.maximum(d0, 1e-12))),
        "mean_distance_sample_m": float(d0.mean()), "mean_distance_refined_m": float(d1.mean()),
        "mean_cost_start": float(c0.mean()), "mean_cost": float(c1.mean())}
  results["confusion"] = {k: v.tolist() for k, v in confusion.items() if v.sum()}
  results["seconds"] = round(time.perf_counter() - t_start, 1)
  return results


PAPER_TABLE2 = {  # paper Table 2 (block towers): top1, top5, top10, RMSE, MAE
    "Frequent": (2.0, 9.7, 13.4, 25.4, 74.4), "Nearest": (1.9, 7.9, 12.4, 41.1, 91.0),
    "Oracle": (6.9, 35.7, 72.0, 18.5, 51.3), "PPD": (16.1, 56.4, 82.5, 9.9, 21.0),
    "PPD+Sample": (18.2, 59.7, 84.0, 8.8, 13.9)}
PAPER_TABLE4 = {"Sample Phys.+Shape": (142.2, 87.1, 70.8, 58.7),
                "Sample Phys.": (89.7, 60.1, 38.7, 22.7), "PPD": (21.0, 15.1, 13.9, 13.2)}


def _sign(on: bool) -> str:
  return "+" if on else "–"


def table2_md(rows: dict, observes: dict) -> list[str]:
  """Markdown lines of Table 2; observes[row] = (texture, physics) booleans."""
  lines = ["| Method | Texture | Physics | Top 1 | Top 5 | Top 10 | RMSE | MAE (mm) |",
           "|---|:-:|:-:|--:|--:|--:|--:|--:|"]
  for name, r in rows.items():
    tex, phys = observes[name]
    lines.append(f"| {name} | {_sign(tex)} | {_sign(phys)} | {r['top1']:.1f} | {r['top5']:.1f} "
                 f"| {r['top10']:.1f} | {r['rmse']:.1f} | {r['mae']:.1f} |")
  return lines


def table4_md(table4: dict) -> list[str]:
  ns = sorted({int(n) for r in table4.values() for n in r})
  lines = ["| trajectory MAE (mm) | " + " | ".join(f"{n}×" for n in ns) + " |",
           "|---|" + "--:|" * len(ns)]
  for name in ("Sample Phys.+Shape", "Sample Phys.", "PPD"):
    if name in table4:
      lines.append(f"| {name} | " + " | ".join(f"{table4[name].get(str(n), float('nan')):.1f}"
                                               for n in ns) + " |")
  return lines


def table5_md(table5: dict) -> list[str]:
  cols = sorted({c for r in table5.values() for c in r if c != "overall"}, key=int)
  lines = ["| density RMSE (slots) | " + " | ".join(f"{c} blocks" for c in cols)
           + " | Overall |", "|---|" + "--:|" * (len(cols) + 1)]
  for name, r in table5.items():
    lines.append(f"| {name} | " + " | ".join(f"{r.get(c, float('nan')):.1f}" for c in cols)
                 + f" | {r['overall']:.1f} |")
  return lines


def results_md(results: dict, command: str = "") -> str:
  """A results.md laid out like the paper's tables, with the paper's numbers beside."""
  m = results["model"]
  observes = {name: (False, False) if name == "Frequent" else (False, True)
              if name == "Nearest" else (True, False) if name == "Oracle"
              else (m["use_image"], m["use_trajectory"]) for name in results["table2"]}
  lines = [f"# Evaluation on `{results['split']}` ({results['objects']} objects)", ""]
  if command:
    lines += ["```", command, "```", ""]
  lines += [f"{results['samples']} density samples per object"
            + (f", refinement {results['refine_steps']} LM steps" if results["refine"] else "")
            + f"; {results['seconds']:.0f} s in all. Shape F1: **{results['f1']:.1f}** "
            "(paper: 97.5).", "", "## Table 2: density and trajectory", ""]
  lines += table2_md(results["table2"], observes)
  lines += ["", "Paper (block towers): " + "; ".join(
      f"{k} {'/'.join(str(v) for v in vals)}" for k, vals in PAPER_TABLE2.items()) + ".", ""]
  if results["table4"]:
    lines += ["## Table 4: best of N samples, trajectory MAE (mm)", ""]
    lines += table4_md(results["table4"])
    lines += ["", "Paper (1×/8×/64×/512×): " + "; ".join(
        f"{k} {'/'.join(str(v) for v in vals)}" for k, vals in PAPER_TABLE4.items()) + ".", ""]
  lines += ["## Table 5: density RMSE by number of blocks", ""]
  lines += table5_md(results["table5"])
  lines += ["", "Paper, Texture + Physics: 2.3 / 4.9 / 7.8 / 10.9, overall 8.0.", ""]
  if results.get("prior_sweep"):
    lines += ["## +Sample selection: distance − τ · log prior", "",
              "| τ (m per nat) | Top 1 | Top 5 | Top 10 | RMSE | MAE (mm) |",
              "|--:|--:|--:|--:|--:|--:|"]
    lines += [f"| {t} | {r['top1']:.1f} | {r['top5']:.1f} | {r['top10']:.1f} | {r['rmse']:.1f} "
              f"| {r['mae']:.1f} |" for t, r in results["prior_sweep"].items()]
    lines += ["", f"Table 2's +Sample rows use τ = {results['prior_weight']}.", ""]
  if "refine_stats" in results:
    r = results["refine_stats"]
    lines += ["## Refinement", "",
              f"Lowered the trajectory distance of the best sample on "
              f"{100 * r['improved_fraction']:.0f}% of objects; median ratio refined / sampled "
              f"{r['median_distance_ratio']:.3f}; mean distance {r['mean_distance_sample_m']:.4f}"
              f" → {r['mean_distance_refined_m']:.4f} m.", ""]
  return "\n".join(lines)


def write_results(results: dict, out_dir: str, command: str = "") -> tuple[str, str]:
  """Writes results.json, results.md and confusion.png (when there is a confusion matrix)."""
  os.makedirs(out_dir, exist_ok=True)
  json_path, md_path = os.path.join(out_dir, "results.json"), os.path.join(out_dir, "results.md")
  with open(json_path, "w") as f:
    json.dump({**results, "command": command}, f, indent=1)
  with open(md_path, "w") as f:
    f.write(results_md(results, command))
  if results.get("confusion"):
    from ppdjax.plots import plot_confusion
    plot_confusion(results["confusion"], os.path.join(out_dir, "confusion.png"))
  return json_path, md_path


def _define_flags():
  from absl import flags
  flags.DEFINE_string("workdir", None, "Training workdir (config.json and checkpoints).",
                      required=True)
  flags.DEFINE_string("data", None, "Dataset directory.", required=True)
  flags.DEFINE_string("out", None, "Output directory (default WORKDIR/eval).")
  flags.DEFINE_string("split", "test", "Split to evaluate.")
  flags.DEFINE_integer("samples", 512, "Density samples per object (and per baseline).")
  flags.DEFINE_bool("refine", False, "Refine the best sample's densities through MJX.")
  flags.DEFINE_integer("refine_steps", 12, "Levenberg–Marquardt iterations.")
  flags.DEFINE_integer("batch_size", 16, "Objects per jitted call.")
  flags.DEFINE_integer("max_objects", 0, "Evaluate only N objects (0: all).")
  flags.DEFINE_enum("subset", "first", ["first", "spread"],
                    "With --max_objects: the first N objects, or N spread over the split.")
  flags.DEFINE_bool("baselines", True, "Also run Frequent, Nearest, Oracle and Table 4's.")
  flags.DEFINE_integer("seed", 0, "Sampling seed.")
  flags.DEFINE_float("prior_weight", 0.0, "+Sample selects by distance - prior_weight * "
                     "log prior (metres per nat; 0: the closest trajectory, as the paper).")


def main(argv):
  import sys

  from absl import flags, logging
  del argv
  logging.set_verbosity(logging.WARNING)
  f = flags.FLAGS
  try:
    results = evaluate(f.workdir, f.data, split=f.split, samples=f.samples, refine=f.refine,
                       refine_steps=f.refine_steps, batch_size=f.batch_size,
                       max_objects=f.max_objects, subset=f.subset, with_baselines=f.baselines,
                       seed=f.seed, prior_weight=f.prior_weight)
  except (checkpoints.CheckpointError, data.DatasetError) as e:
    sys.exit(f"error: {e}")
  command = "python -m ppdjax.evaluate " + " ".join(sys.argv[1:])
  paths = write_results(results, f.out or os.path.join(f.workdir, "eval"), command)
  best = results["table2"].get("PPD+Sample+Refine") or results["table2"].get("PPD+Sample")
  print(f"F1 {results['f1']:.1f}; best row: top1 {best['top1']:.1f}, RMSE {best['rmse']:.2f}, "
        f"MAE {best['mae']:.1f} mm -> {paths[0]}, {paths[1]}")


if __name__ == "__main__":
  from absl import app
  _define_flags()
  app.run(main)
