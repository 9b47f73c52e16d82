"""How often refinement improves on the best sample, and by how much (true shapes).

  python experiments/refine_study.py --objects 24 --samples 64 --out experiments/results/refine_study
  python experiments/refine_study.py --compare=jacobians --objects 12 --samples 32 \
      --out experiments/results/refine_jacobians

For random towers (2-5 blocks, the dataset's materials and densities) observed under the
paper's pushes: draw `samples` uniform density assignments on the true shape ("Sample
Phys."), keep the one closest in trajectory, then refine it by Levenberg–Marquardt
through the JAX engine, in variants from the same start. `--compare=schedules`: two
horizon schedules, the library's (`refine.horizon_schedule`, doubling from 8 steps) and
the single switch it replaced (the first 64 steps for the first half of the passes, then
all). `--compare=jacobians`: the library's schedule with the Jacobian by forward mode and
by forward differences (`refine.difference_jacobian`) at four steps and by central
differences at two. Isolates the physics
steps from the network. Writes OUT.json and OUT.md.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.infer import refine, sampling
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim import rollout_mjx
from ppdjax.sim.rollout_mjx import settings_for


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--objects", type=int, default=24)
  parser.add_argument("--samples", type=int, default=64)
  parser.add_argument("--steps", type=int, default=12)
  parser.add_argument("--seed", type=int, default=5)
  parser.add_argument("--compare", default="schedules", choices=("schedules", "jacobians"))
  parser.add_argument("--backend", default="mjx", choices=("mjx", "box_plane"),
                      help="the JAX engine that observes and refines")
  parser.add_argument("--out", default="experiments/results/refine_study")
  args = parser.parse_args()
  pushes = default_pushes()
  settings = settings_for(args.backend)
  t = 256  # the dataset's trajectory length (ppdjax.simulate's default)
  passes = np.arange(args.steps + 1)
  schedules = {"doubling": refine.horizon_schedule(args.steps, 8, t),
               "switch": np.where(passes < args.steps // 2, 64, t)}
  if args.compare == "schedules":  # name: (horizons, jacobian, difference step)
    variants = {name: (h, "forward", None) for name, h in schedules.items()}
  else:
    variants = {"forward mode": (schedules["doubling"], "forward", None)}
    variants.update({f"differences {h:g}": (schedules["doubling"], "differences", h)
                     for h in (1e-2, 1e-3, 3e-4, 1e-4)})
    variants.update({f"central {h:g}": (schedules["doubling"], "central", h)
                     for h in (1e-3, 3e-3)})
  true = jax.tree.map(jnp.asarray, ppdjax.sample_towers(args.seed, args.objects))

  @jax.jit
  def run(true, key):
    obs = rollout_mjx.simulate(true, pushes, settings=settings)
    keys = jax.random.split(key, args.objects)
    sel = jax.vmap(lambda p, o, k: sampling.select_densities(
        p, jnp.zeros((p.num_slots, NUM_DENSITY_SLOTS)), o, pushes, num_samples=args.samples,
        key=k, include_mode=False, settings=settings))(true, obs, keys)
    start = true.replace(density=sel.density)
    out = {}
    for name, (horizons, jacobian, step) in variants.items():
      extra = {} if step is None else {"difference_step": step}
      refined, _ = jax.vmap(lambda p, o, h=horizons, j=jacobian, e=extra: refine.refine_densities(
          p, o, pushes, steps=args.steps, horizons=h, jacobian=j, settings=settings, **e))(
              start, obs)
      sim = rollout_mjx.simulate(refined, pushes, settings=settings)
      out[name] = (refined.density, metrics.trajectory_distance(sim, obs),
                   metrics.trajectory_mae(sim, obs))
    return obs, sel.density, sel.score, sel.mae.min(-1), out

  t0 = time.perf_counter()
  obs, d_sample, dist0, mae0, refined = jax.device_get(run(true, jax.random.key(args.seed)))
  refined = {name: refined[name] for name in variants}  # the variants' order, not sorted
  seconds = time.perf_counter() - t0
  valid = np.asarray(true.valid)
  slot = lambda d: d / 100.0 - 1.0
  n = valid.sum()
  true_slot = slot(np.asarray(true.density))
  err = lambda d: np.where(valid, np.rint(slot(d)) - true_slot, 0)
  rel = lambda d: np.abs(d / np.where(valid, np.asarray(true.density), 1.0) - 1.0)[valid]
  moved = np.linalg.norm(obs[..., :3] - obs[:, :, :1, :3], axis=-1).mean((1, 2))
  columns = {"best sample": (d_sample, dist0, mae0)}
  columns.update({f"+ refinement ({name})": v for name, v in refined.items()})

  def column(d, dist, mae):
    e = err(d)
    return {"distance_m": float(dist.mean()), "mae_mm": float(mae.mean()),
            "rmse_slots": float(np.sqrt((e ** 2).sum() / n)),
            "top1_percent": float(100 * ((e == 0) & valid).sum() / n),
            "within_5_percent": float(np.mean(rel(d) < 0.05)),
            "lowered_distance": float(np.mean(dist < dist0 - 1e-9)),
            "median_distance_ratio": float(np.median(dist / np.maximum(dist0, 1e-12)))}

  result = {
      "objects": args.objects, "boxes": int(n), "samples": args.samples,
      "lm_steps": args.steps, "seconds_incl_compile": round(seconds, 1),
      "device": jax.devices()[0].device_kind,
      "compare": args.compare, "backend": args.backend,
      "schedules": {k: v.tolist() for k, v in schedules.items()},
      "variants": {k: {"jacobian": j, "difference_step": st}
                   for k, (_, j, st) in variants.items()},
      "columns": {k: column(*v) for k, v in columns.items()},
      "per_object": [{"blocks": int(v.sum()), "mean_displacement_m": float(m)}
                     for v, m in zip(valid, moved)],
  }
  with open(args.out + ".json", "w") as f:
    json.dump(result, f, indent=1)
  md = ["# Refinement after sampling, on true shapes", "", "```",
        f"python experiments/refine_study.py --objects {args.objects} --samples {args.samples}"
        f" --steps {args.steps} --seed {args.seed} --compare={args.compare}"
        f" --backend={args.backend}", "```", "",
        f"{args.objects} random towers (2-5 blocks, {n} boxes) observed by the "
        f"{args.backend} engine, best of {args.samples} uniform density samples, then "
        f"{args.steps} LM steps from it in each variant ({args.compare}); "
        f"{result['device']}, {seconds:.0f} s with compilation.", "",
        "Horizons (trajectory steps fitted per pass): doubling (the library's) "
        f"{schedules['doubling'].tolist()}; switch (before) {schedules['switch'].tolist()}.",
        "", "| | " + " | ".join(columns) + " |", "|---|" + "--:|" * len(columns)]
  for name, key, fmt in (("trajectory distance (m)", "distance_m", "{:.4f}"),
                         ("trajectory MAE (mm)", "mae_mm", "{:.1f}"),
                         ("density RMSE (slots)", "rmse_slots", "{:.2f}"),
                         ("density top-1 (%)", "top1_percent", "{:.1f}"),
                         ("boxes within 5% of the true density", "within_5_percent", "{:.2f}"),
                         ("objects whose distance refinement lowered", "lowered_distance",
                          "{:.2f}"),
                         ("median distance ratio to the best sample", "median_distance_ratio",
                          "{:.3f}")):
    md.append(f"| {name} | " + " | ".join(
        "–" if col == "best sample" and key in ("lowered_distance", "median_distance_ratio")
        else fmt.format(c[key]) for col, c in result["columns"].items()) + " |")
  first = next(iter(refined))
  same = {name: float(np.mean((np.rint(slot(v[0])) == np.rint(slot(refined[first][0])))[valid]))
          for name, v in refined.items() if name != first}
  result["same_slot_as_first"] = same
  if same:
    md += ["", f"Boxes whose refined slot equals {first}'s: " + ", ".join(
        f"{name} {100 * v:.1f} %" for name, v in same.items()) + "."]
    with open(args.out + ".json", "w") as f:
      json.dump(result, f, indent=1)
  with open(args.out + ".md", "w") as f:
    f.write("\n".join(md) + "\n")
  print("\n".join(md))


if __name__ == "__main__":
  main()
