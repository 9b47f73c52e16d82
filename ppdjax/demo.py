"""Demo: the whole pipeline on one preset (the README's first command).

  python -m ppdjax.demo --config=ppdjax/configs/tiny.py --out=out/demo

1. a random block tower under the paper's four pushes, simulated in MJX (and MuJoCo C):
   OUT/trajectories.png, OUT/summary.md, OUT/summary.json;
2. the preset's block-tower dataset: OUT/blocks (with its card.md);
3. the PPD network trained on it: OUT/train (checkpoints, metrics.jsonl,
   learning_curve.png);
4. its evaluation on the test split, with the baselines: OUT/eval (results.md,
   results.json, confusion.png);
5. one test tower decomposed by the jitted `decompose`: OUT/decomposition.png (input
   image, recovered boxes coloured by density, and the truth).
Steps 1-3 resume where a previous run stopped.
"""

from __future__ import annotations

import json
import os
import time

from absl import app, flags, logging
from ml_collections import config_flags


def _define_flags():  # at run time only, so other entry points can be imported beside this
  config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
  flags.DEFINE_string("out", "out/demo", "Output directory.")


def run_demo(config, out_dir: str) -> dict:
  """Simulates one tower and writes the plot and summary; returns the summary."""
  import jax
  import jax.numpy as jnp
  import numpy as np

  from ppdjax import physics, scene, towers
  from ppdjax.plots import plot_trajectories

  cfg = config.demo
  os.makedirs(out_dir, exist_ok=True)
  rng = np.random.default_rng(config.seed)
  prims, names = towers.sample_tower(rng, cfg.num_blocks)
  prims.validate()
  pushes = physics.default_pushes()
  p = jax.tree.map(jnp.asarray, prims)
  props = physics.mass_properties(p)

  print(f"[1/3] simulating {len(names)} blocks x {pushes.num} pushes x {cfg.steps} steps "
        f"with {cfg.backend} (the first call compiles)...", flush=True)
  t0 = time.perf_counter()
  traj = np.asarray(physics.simulate(prims, pushes, steps=cfg.steps, backend=cfg.backend))
  seconds = time.perf_counter() - t0
  ref = None
  if cfg.reference_backend:
    print(f"[2/3] the same rollouts in {cfg.reference_backend} for comparison...", flush=True)
    ref = np.asarray(physics.simulate(prims, pushes, steps=cfg.steps,
                                      backend=cfg.reference_backend))

  rest = np.asarray(scene.rest_position(p))
  first_speed = np.linalg.norm(traj[:, 0, :3] - rest, axis=-1) / scene.TIMESTEP
  summary = {
      "config": config.name, "seed": config.seed, "backend": cfg.backend,
      "blocks": [{"material": n, "density": float(d), "half_size": hs.round(4).tolist(),
                  "pos": ps.round(4).tolist()}
                 for n, d, hs, ps in zip(names, np.asarray(prims.density), np.asarray(
                     prims.half_size), np.asarray(prims.pos))],
      "mass_kg": float(props.mass), "com_m": [round(float(c), 4) for c in np.asarray(props.com)],
      "push_points_m": np.asarray(physics.push_points(p, pushes)).round(4).tolist(),
      "speed_after_push_m_s": [round(float(v), 3) for v in first_speed],
      "final_displacement_m": np.linalg.norm(traj[:, -1, :3] - rest, axis=-1).round(3).tolist(),
      "simulate_seconds_incl_compile": round(seconds, 2),
  }
  if ref is not None:
    gap = np.linalg.norm(traj[..., :3] - ref[..., :3], axis=-1) * 1e3
    summary["gap_to_reference_mm"] = {
        "first_0.1s_max": gap[:, :30].max(-1).round(3).tolist(),
        "final": gap[:, -1].round(2).tolist()}

  print("[3/3] writing plot and summary...", flush=True)
  plot_trajectories(prims, pushes, traj, ref, os.path.join(out_dir, "trajectories.png"),
                    labels=(cfg.backend, cfg.reference_backend))
  with open(os.path.join(out_dir, "summary.json"), "w") as f:
    json.dump(summary, f, indent=1)
  with open(os.path.join(out_dir, "summary.md"), "w") as f:
    f.write(_markdown(summary))
  return summary


def _markdown(s: dict) -> str:
  lines = [f"# ppdjax demo ({s['config']} preset, seed {s['seed']})", "",
           f"Tower of {len(s['blocks'])} blocks, mass {s['mass_kg']:.1f} kg, centre of mass "
           f"({', '.join(f'{c:.3f}' for c in s['com_m'])}) m in the object frame. "
           f"Engine: {s['backend']}.", "",
           "| block | material | density (kg/m³) |", "|---|---|---|"]
  lines += [f"| {i} | {b['material']} | {b['density']:.0f} |" for i, b in enumerate(s["blocks"])]
  lines += ["", "| push | source | speed after push (m/s) | displacement after 256 steps (m) "
            "| gap to reference, first 0.1 s / final (mm) |", "|---|---|---|---|---|"]
  sources = ["(+1, -1, +1)", "(-1, -1, +1)", "(+1, -1, -1)", "(-1, -1, -1)"]
  for i in range(len(s["speed_after_push_m_s"])):
    gap = s.get("gap_to_reference_mm")
    gap_txt = f"{gap['first_0.1s_max'][i]:.3f} / {gap['final'][i]:.2f}" if gap else "-"
    lines.append(f"| {i} | {sources[i] if i < 4 else '-'} | {s['speed_after_push_m_s'][i]:.2f} "
                 f"| {s['final_displacement_m'][i]:.3f} | {gap_txt} |")
  lines += ["", "![trajectories](trajectories.png)", ""]
  return "\n".join(lines)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  out = flags.FLAGS.out
  config = flags.FLAGS.config
  summary = run_demo(config, out)
  print(f"physics: {out}/trajectories.png, summary.md, summary.json "
        f"(speeds after push {summary['speed_after_push_m_s']} m/s)", flush=True)
  from ppdjax import generate, train
  print(f"dataset: {config.data.num_towers} towers x {config.data.configs_per_tower} "
        f"configurations -> {out}/blocks", flush=True)
  generate.generate(config, os.path.join(out, "blocks"))
  print(f"training ({config.train.geometry_steps} geometry + {config.train.joint_steps} joint "
        f"steps) -> {out}/train", flush=True)
  final = train.train_and_evaluate(config, os.path.join(out, "blocks"),
                                   os.path.join(out, "train"))
  if final:
    print("validation: " + ", ".join(f"{k} {v:.3g}" for k, v in final.items()))
  run_evaluation(config, os.path.join(out, "blocks"), os.path.join(out, "train"), out)
  print(f"done: {out}/summary.md, {out}/blocks/card.md, {out}/train/learning_curve.png, "
        f"{out}/eval/results.md, {out}/decomposition.png")


def run_evaluation(config, blocks: str, workdir: str, out: str) -> dict:
  """Evaluates a trained model and decomposes one test tower (steps 4 and 5)."""
  import jax
  import numpy as np

  from ppdjax import checkpoints, data, evaluate, inference
  from ppdjax.plots import plot_decomposition

  cfg = config.eval
  trained = checkpoints.load(workdir)
  print(f"evaluating on the test split with {cfg.samples} density samples per object "
        f"(compiles once) -> {out}/eval", flush=True)
  results = evaluate.evaluate(trained, blocks, samples=cfg.samples, refine=cfg.refine,
                              refine_steps=cfg.refine_steps, batch_size=cfg.batch_size,
                              prior_weight=cfg.prior_weight)
  evaluate.write_results(results, os.path.join(out, "eval"),
                         f"python -m ppdjax.evaluate --workdir={workdir} --data={blocks} "
                         f"--samples={cfg.samples}" + (" --refine" if cfg.refine else ""))
  row = results["table2"]["PPD+Sample"]
  print(f"test: shape F1 {results['f1']:.1f}, +Sample top-1 {row['top1']:.1f}%, RMSE "
        f"{row['rmse']:.1f} slots, trajectory MAE {row['mae']:.0f} mm", flush=True)
  print("decomposing one test tower with the jitted decompose()...", flush=True)
  sample = data.open_dataset(blocks, "test")[0]
  decompose = inference.make_decompose_fn(trained, num_samples=cfg.samples, refine=cfg.refine,
                                          refine_steps=cfg.refine_steps,
                                          prior_weight=cfg.prior_weight)
  got = decompose({k: sample[k] for k in ("voxels", "image", "trajectories")},
                  jax.random.key(config.seed))
  prims = jax.device_get(got.primitives)
  plot_decomposition(sample["image"], prims, os.path.join(out, "decomposition.png"),
                     true=sample["primitives"],
                     title=f"trajectory distance {float(got.score) * 1e3:.0f} mm; densities "
                           f"{np.asarray(prims.density)[np.asarray(prims.valid)].round()} kg/m³")
  return results


if __name__ == "__main__":
  _define_flags()
  app.run(main)
