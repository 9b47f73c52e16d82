"""Benchmark: steps/s of ppdjax.simulate, MJX and the box-plane step (accelerator) against
MuJoCo C (all CPU cores).

Both engines run in this one process on the same random towers under the paper's four
pushes (rollouts = towers x 4). Each MJX variant is timed after compilation and checked
against the C trajectories of the same rollouts (the agreement columns, in mm of the
object-frame origin). Prints a markdown table and writes JSON.

  python experiments/benchmarks/bench_physics.py --sizes 2048,65536 --out bench.json
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time

import jax
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.sim.box_plane import BoxPlaneSettings
from ppdjax.sim.rollout_mjx import MjxSettings


def _v(iterations, ls, contacts=-1, fixed=True, push=(100, 50), chol=False, unroll=1):
  return MjxSettings(iterations=iterations, ls_iterations=ls, max_contact_points=contacts,
                     fixed_iterations=fixed, push_iterations=push[0], push_ls_iterations=push[1],
                     unrolled_cholesky=chol, unroll=unroll)


# A ladder: each row adds one change to the row above; the last is the package default
# (ppdjax.sim.rollout_mjx.MjxSettings()). From the second row on, the push step is solved to
# convergence and the settings apply to the steps after it.
VARIANTS = {
    "MJX as shipped (Newton 100 / ls 50)": _v(100, 50, fixed=False),
    "Newton 4 / ls 8 (push step converged)": _v(4, 8, fixed=False),
    "+ 8 deepest contacts": _v(4, 8, 8, fixed=False),
    "+ fixed iterations (no while_loop)": _v(4, 8, 8),
    "+ push step fixed 8 / ls 4": _v(4, 8, 8, push=(8, 4)),
    "+ line search 2": _v(4, 2, 8, push=(8, 4)),
    "+ unrolled Cholesky": _v(4, 2, 8, push=(8, 4), chol=True),
    "+ Newton 3 (default)": MjxSettings(),
    # explored, not in the ladder
    "Newton 2 / ls 4 (explored)": _v(2, 4, 8, push=(8, 4), chol=True),
    "scan unroll 2": _v(3, 2, 8, push=(8, 4), chol=True, unroll=2),
    # the step written for this scene (ppdjax.sim.box_plane), MuJoCo C's box-plane contacts
    # (its XLA reference; "kernel" rows run the same step as one Pallas kernel)
    "box-plane step: Newton 3 / ls 2 (all contacts)": BoxPlaneSettings(
        max_contacts=0, kernel="reference"),
    "box-plane step: Newton 3 / ls 2 (8 deepest contacts; default)": BoxPlaneSettings(
        kernel="reference"),
    "box-plane step: Newton 2 / ls 2 (8 deepest contacts)": BoxPlaneSettings(
        iterations=2, max_contacts=8, kernel="reference"),
    "box-plane step: Newton 4 / ls 3": BoxPlaneSettings(iterations=4, ls_iterations=3,
                                                        kernel="reference"),
    "box-plane step: converged (Newton 10 / ls 6)": BoxPlaneSettings(
        iterations=10, ls_iterations=6, push_iterations=10, push_ls_iterations=6,
        max_contacts=0, kernel="reference"),
    "box-plane step: Pallas kernel (default on a GPU)": BoxPlaneSettings(kernel="pallas"),
}
BOX_PLANE = [name for name in VARIANTS if name.startswith("box-plane")]
assert VARIANTS["+ Newton 3 (default)"] == _v(3, 2, 8, push=(8, 4), chol=True)

flags.DEFINE_string("sizes", "2048,65536", "Rollout counts, comma-separated (multiples of 4).")
flags.DEFINE_string("variants", ",".join(list(VARIANTS)[:8] + BOX_PLANE[:2]),
                    "Comma-separated variants (default: the MJX ladder and the box-plane "
                    "step's default).")
flags.DEFINE_integer("steps", 256, "Simulation steps a rollout.")
flags.DEFINE_integer("seed", 0, "Tower seed.")
flags.DEFINE_integer("repeats", 3, "Warm calls timed (median).")
flags.DEFINE_string("out", "", "JSON file for the results.")
FLAGS = flags.FLAGS


def agreement(traj, ref) -> dict:
  """Gap statistics (mm) between two (N, P, T, 7) trajectory sets, per rollout."""
  gap = np.linalg.norm(np.asarray(traj)[..., :3] - np.asarray(ref)[..., :3], axis=-1) * 1e3
  gap = gap.reshape(-1, gap.shape[-1])
  early = gap[:, :30].max(-1)  # before landing events: the first 0.1 s
  return {"early_p90_mm": float(np.percentile(early, 90)),
          "early_max_mm": float(early.max()),
          "median_mm": float(np.median(gap)),
          "final_p50_mm": float(np.percentile(gap[:, -1], 50)),
          "final_p90_mm": float(np.percentile(gap[:, -1], 90)),
          "final_max_mm": float(gap[:, -1].max())}


def timed(fn, repeats):
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    out = fn()
    jax.block_until_ready(out)
    times.append(time.perf_counter() - t)
  return out, float(np.median(times))


def main(argv):
  del argv
  pushes = ppdjax.default_pushes()
  rows = []
  meta = {"device": str(jax.devices()[0].device_kind), "backend": jax.default_backend(),
          "cpu_count": os.cpu_count(), "jax": jax.__version__, "python": platform.python_version(),
          "xla_flags": os.environ.get("XLA_FLAGS", ""), "steps": FLAGS.steps}

  def save():
    if FLAGS.out:
      with open(FLAGS.out, "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)

  for size in (int(s) for s in FLAGS.sizes.split(",")):
    prims = ppdjax.sample_towers(FLAGS.seed, size // pushes.num)
    rollouts = size // pushes.num * pushes.num
    ppdjax.simulate(prims, pushes, steps=2, backend="mujoco")  # compiles the preprocessing
    ref, t_c = timed(lambda: ppdjax.simulate(prims, pushes, steps=FLAGS.steps,
                                              backend="mujoco"), max(1, FLAGS.repeats - 1))
    c_rate = rollouts * FLAGS.steps / t_c
    rows.append({"rollouts": rollouts, "engine": f"MuJoCo C, mujoco.batch, {os.cpu_count()} threads",
                 "seconds": t_c, "steps_per_s": c_rate, "ratio": 1.0})
    print(f"[{rollouts}] C: {t_c:.2f} s, {c_rate / 1e6:.2f} M steps/s", flush=True)
    save()
    for name in FLAGS.variants.split(","):
      settings = VARIANTS[name]
      backend = "box_plane" if isinstance(settings, BoxPlaneSettings) else "mjx"
      run = lambda s=settings, b=backend: ppdjax.simulate(prims, pushes, steps=FLAGS.steps,
                                                          backend=b, settings=s)
      t0 = time.perf_counter()
      jax.block_until_ready(run())
      compile_s = time.perf_counter() - t0
      out, t = timed(run, FLAGS.repeats)
      rate = rollouts * FLAGS.steps / t
      engine = name if backend == "box_plane" else f"MJX {name}"
      row = {"rollouts": rollouts, "engine": engine, "settings": dataclasses.asdict(settings),
             "seconds": t, "compile_s": compile_s, "steps_per_s": rate, "ratio": rate / c_rate,
             **agreement(out, ref)}
      rows.append(row)
      print(f"[{rollouts}] {name}: {t:.3f} s, {rate / 1e6:.2f} M steps/s, {rate / c_rate:.2f}x C,"
            f" early p90 {row['early_p90_mm']:.3f} mm, median {row['median_mm']:.3f} mm"
            f" (compile {compile_s:.0f} s)", flush=True)
      save()
  print(f"\n{meta}\n")
  print(table(rows))


def table(rows) -> str:
  lines = ["| rollouts | engine | s | M steps/s | × C | first 0.1 s p90 (mm) | median (mm) "
           "| final p50 / p90 / max (mm) |", "|---|---|---|---|---|---|---|---|"]
  for r in rows:
    agree = ("reference | reference | reference" if "early_p90_mm" not in r else
             f"{r['early_p90_mm']:.3f} | {r['median_mm']:.3f} | {r['final_p50_mm']:.2f} / "
             f"{r['final_p90_mm']:.1f} / {r['final_max_mm']:.1f}")
    lines.append(f"| {r['rollouts']} | {r['engine']} | {r['seconds']:.3f} | "
                 f"{r['steps_per_s'] / 1e6:.2f} | {r['ratio']:.2f} | {agree} |")
  return "\n".join(lines)


if __name__ == "__main__":
  app.run(main)
