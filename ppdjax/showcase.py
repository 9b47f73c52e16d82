"""What `make demo` shows: the shipped model at work, the physics, and a smoke run of training.

`shipped_example` decomposes the shipped example tower with the shipped model;
`physics_tour` simulates one random tower under the paper's pushes; `smoke_run` runs the
tiny generate -> train -> evaluate -> decompose path, which checks that the training
pipeline runs end to end (its numbers are not what the method can do).
"""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import OBS_KEYS, TIMESTEP
from ppdjax.dataset import generation, storage, towers
from ppdjax.infer import example
from ppdjax.eval import evaluation
from ppdjax.report import markdown
from ppdjax.infer.decompose import make_decompose_fn, model_settings
from ppdjax.report.plots import plot_decomposition, plot_trajectories
from ppdjax.sim.mass import mass_properties
from ppdjax.sim.pushes import default_pushes, push_points
from ppdjax.sim.scene import rest_position
from ppdjax.sim.simulate import simulate
from ppdjax.training import checkpoints, loop


def shipped_example(model_dir: str, example_path: str, out_dir: str, samples: int,
                    image_fit: bool = True) -> dict:
  """Decomposes the example tower with the model's settings (`samples` candidates; without
  the image fit unless `image_fit`); writes OUT/example.png and OUT/example.md (the answer
  beside the truth); returns `example.decompose_example`'s record."""
  os.makedirs(out_dir, exist_ok=True)
  config = model_settings(model_dir)
  config = config.replace(**{"select.samples": samples,
                             "fit.image": config.fit.image and image_fit})
  r = example.decompose_example(model_dir, example_path, os.path.join(out_dir, "example.png"),
                                config=config)
  with open(os.path.join(out_dir, "example.md"), "w") as f:
    f.write(example.report_md(r, model_dir, example_path))
  return r


def physics_rollouts(config) -> dict:
  """One random tower (`config.seed`) simulated under the paper's four pushes in
  `config.demo.backend` and its reference engine: what `physics_tour` shows. Thread-safe
  (it draws nothing), so the demo runs it beside the shipped example: both are mostly
  single-threaded compilation on a CPU."""
  cfg = config.demo
  prims, names = towers.sample_tower(np.random.default_rng(config.seed), cfg.num_blocks)
  prims.validate()
  pushes = default_pushes()
  t0 = time.perf_counter()
  traj = np.asarray(simulate(prims, pushes, steps=cfg.steps, backend=cfg.backend))
  seconds = time.perf_counter() - t0
  ref = None
  if cfg.reference_backend:
    ref = np.asarray(simulate(prims, pushes, steps=cfg.steps,
                              backend=cfg.reference_backend))
  return {"prims": prims, "names": names, "pushes": pushes, "traj": traj, "ref": ref,
          "seconds": seconds}


def physics_tour(config, out_dir: str, rollouts: dict | None = None) -> dict:
  """Writes OUT/trajectories.png, summary.md and summary.json for `physics_rollouts`
  (made here unless given); returns the summary."""
  cfg = config.demo
  os.makedirs(out_dir, exist_ok=True)
  r = rollouts or physics_rollouts(config)
  prims, names, pushes, traj, ref = r["prims"], r["names"], r["pushes"], r["traj"], r["ref"]
  p = jax.tree.map(jnp.asarray, prims)
  props = mass_properties(p)

  rest = np.asarray(rest_position(p))
  first_speed = np.linalg.norm(traj[:, 0, :3] - rest, axis=-1) / TIMESTEP
  summary = {
      "config": config.name, "seed": config.seed, "backend": cfg.backend, "steps": cfg.steps,
      "push_sources": np.asarray(pushes.sources).round(3).tolist(),
      "blocks": [{"material": n, "density": float(d), "half_size": hs.round(4).tolist(),
                  "pos": ps.round(4).tolist()}
                 for n, d, hs, ps in zip(names, np.asarray(prims.density), np.asarray(
                     prims.half_size), np.asarray(prims.pos))],
      "mass_kg": float(props.mass), "com_m": [round(float(c), 4) for c in np.asarray(props.com)],
      "push_points_m": np.asarray(push_points(p, pushes)).round(4).tolist(),
      "speed_after_push_m_s": [round(float(v), 3) for v in first_speed],
      "final_displacement_m": np.linalg.norm(traj[:, -1, :3] - rest, axis=-1).round(3).tolist(),
      "simulate_seconds_incl_compile": round(r["seconds"], 2),
  }
  if ref is not None:
    gap = np.linalg.norm(traj[..., :3] - ref[..., :3], axis=-1) * 1e3
    summary["gap_to_reference_mm"] = {
        "first_0.1s_max": gap[:, :30].max(-1).round(3).tolist(),
        "final": gap[:, -1].round(2).tolist()}

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
  lines += ["", f"| push | source | speed after push (m/s) | displacement after {s['steps']} "
            "steps (m) | gap to reference, first 0.1 s / final (mm) |", "|---|---|---|---|---|"]
  sources = ["(" + ", ".join(f"{v:+g}" for v in src) + ")" for src in s["push_sources"]]
  for i in range(len(s["speed_after_push_m_s"])):
    gap = s.get("gap_to_reference_mm")
    gap_txt = f"{gap['first_0.1s_max'][i]:.3f} / {gap['final'][i]:.2f}" if gap else "-"
    lines.append(f"| {i} | {sources[i]} | {s['speed_after_push_m_s'][i]:.2f} "
                 f"| {s['final_displacement_m'][i]:.3f} | {gap_txt} |")
  lines += ["", "![trajectories](trajectories.png)", ""]
  return "\n".join(lines)


def smoke_run(config, out_dir: str) -> dict:
  """The preset's dataset (OUT/blocks), training (OUT/train), evaluation (OUT/eval) and one
  decomposed test tower (OUT/decomposition.png); the first two resume. Returns the
  evaluation's results."""
  blocks, workdir = os.path.join(out_dir, "blocks"), os.path.join(out_dir, "train")
  print(f"  dataset: {config.data.num_towers} towers x {config.data.configs_per_tower} "
        f"configurations -> {blocks}", flush=True)
  generation.generate(config, blocks)
  print(f"  training ({config.train.geometry_steps} geometry + {config.train.joint_steps} "
        f"joint steps) -> {workdir}", flush=True)
  final = loop.train_and_evaluate(config, blocks, workdir)
  if final:
    print("  validation: " + ", ".join(f"{k} {v:.3g}" for k, v in final.items()), flush=True)
  return evaluate_and_decompose(config, blocks, workdir, out_dir)


def evaluate_and_decompose(config, blocks: str, workdir: str, out: str) -> dict:
  """Evaluates a trained model on the test split (OUT/eval) and decomposes one test tower
  (OUT/decomposition.png); returns the evaluation's results."""
  trained = checkpoints.load(workdir)
  print(f"  evaluating on the test split with {trained[1].eval.samples} density samples per "
        "object "
        f"(compiles once) -> {out}/eval", flush=True)
  results = evaluation.evaluate(trained, blocks)  # the model's own settings, as decompose
  command = f"python -m ppdjax.evaluate --workdir={workdir} --data={blocks}"
  markdown.write_results(results, os.path.join(out, "eval"), command, config=trained[1],
                         weights=trained[0])
  row = results["table2"][results["headline"]]
  print(f"  test: shape F1 {results['f1']:.1f}, {results['headline']} top-1 {row['top1']:.1f}%"
        f", RMSE {row['rmse']:.1f} slots, trajectory MAE {row['mae']:.0f} mm", flush=True)
  print("  decomposing one test tower with the jitted decompose()...", flush=True)
  sample = storage.open_dataset(blocks, "test")[0]
  decompose = make_decompose_fn(trained)  # the same settings as the evaluation above
  got = decompose({k: sample[k] for k in OBS_KEYS}, jax.random.key(config.seed))
  prims = jax.device_get(got.primitives)
  plot_decomposition(sample["image"], prims, os.path.join(out, "decomposition.png"),
                     true=sample["primitives"],
                     title=f"trajectory distance {float(got.score) * 1e3:.0f} mm; densities "
                           f"{np.asarray(prims.density)[np.asarray(prims.valid)].round()} kg/m³")
  return results
