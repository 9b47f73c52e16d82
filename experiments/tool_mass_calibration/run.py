"""Does +Sample on a tool's true boxes pick the labels' densities once the candidates are
simulated at the tool's mass? (issue 18: the boxes weigh a median 1.29x the tool, so the
closest box trajectory needs densities below the labels.)

  python experiments/tool_mass_calibration/run.py --tools=100 --seed=7 --calibrate_seed=8

For fresh procedural tools (`tools.sample_tools`, normalised as the dataset does), MuJoCo
C under the tools' four pushes: the tool's own trajectories (`tool_scene.simulate_tool`)
are the observation; the candidates are its true boxes (`mesh_boxes.boxes_of_parts`)
with `--candidates` slot assignments: the labels, and the labels moved by a uniform
integer in [-`--radius`, `--radius`] per box (clipped to the 100 slots), so the truth is
always among them. Each candidate is simulated with its densities times a factor and the
closest trajectory (`metrics.trajectory_distance`, what +Sample minimises, over all the
steps or the first 128, 64, 32 or 16: `selection_horizon`) is picked; its slots are scored
against the labels (top-1 per box, RMSE in slots) for three factors:
  * 1: the candidates as they are (the paper's rule; the evaluation's today);
  * 1 / c: c the median box mass / tool mass over `--calibrate_tools` tools of
    `--calibrate_seed` (learned on other tools, usable at test time);
  * tool mass / box mass of the tool itself (an oracle: the factor no test can know).
Writes OUT/results.json and OUT/results.md.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from absl import app, flags

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS, density_to_slot, slot_to_density
from ppdjax.dataset import meshes, tool_scene, tools
from ppdjax.dataset.mesh_boxes import boxes_of_parts

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tool_studies.common import (define_study_flags, over_tools,  # noqa: E402
                                 simulate_candidates, write)

FLAGS = flags.FLAGS

FACTORS = ("paper (x1)", "calibrated (x1/c)", "oracle (tool's own)")
HORIZONS = (0, 128, 64, 32, 16)  # steps of 1/300 s the distance reads (0: all 256)


def masses(parts, densities, prims) -> tuple[float, float]:
  """(tool mass, its boxes' mass at their labels), kg."""
  tool = float(sum(abs(p.volume) * d for p, d in zip(parts, densities)))
  return tool, float(ppdjax.mass_properties(prims).mass)


def calibration(seed: int, count: int) -> float:
  """The median box mass / tool mass over `count` tools of `seed`."""
  ratios = []
  for tool in tools.sample_tools(seed, count):
    parts, _ = meshes.normalize(list(tool.parts))
    prims, _ = boxes_of_parts(parts, tool.densities)
    tool_mass, box_mass = masses(parts, tool.densities, prims)
    ratios.append(box_mass / tool_mass)
  return float(np.median(ratios))


def candidate_slots(labels: np.ndarray, valid: np.ndarray, count: int, radius: int,
                    rng: np.random.Generator) -> np.ndarray:
  """(count, K) slots: the labels first, then each valid box's label moved by a uniform
  integer in [-radius, radius], clipped to the slots (invalid boxes keep their label)."""
  moves = rng.integers(-radius, radius + 1, size=(count, len(labels))) * valid
  moves[0] = 0
  return np.clip(labels + moves, 0, NUM_DENSITY_SLOTS - 1)


def study_tool(tool, c: float, count: int, radius: int, rng) -> dict | None:
  """The pick under each factor; None where MuJoCo diverges on the tool."""
  parts, _ = meshes.normalize(list(tool.parts))
  try:
    seen = tool_scene.simulate_tool(parts, tool.densities)
  except RuntimeError:
    return None
  prims, _ = boxes_of_parts(parts, tool.densities)
  valid = np.asarray(prims.valid)
  labels = density_to_slot(np.asarray(prims.density))
  tool_mass, box_mass = masses(parts, tool.densities, prims)
  slots = candidate_slots(labels, valid, count, radius, rng)
  off = (slots - labels)[:, valid].astype(float)
  out = {"category": tool.category, "box_mass_ratio": box_mass / tool_mass,
         "labels": labels[valid].tolist(),  # and what a candidate drawn at random scores:
         "pool": {"square_error": (off ** 2).mean(0).tolist(), "hit": (off == 0).mean(0).tolist()}}
  for name, factor in zip(FACTORS, (1.0, 1.0 / c, tool_mass / box_mass)):
    traj = simulate_candidates(prims, slot_to_density(slots) * factor, tool_scene.tool_pushes())
    dist = np.asarray(metrics.horizon_distances(traj, seen, HORIZONS))  # (count, H)
    for h, d in zip(HORIZONS, dist.T):
      out[_key(name, h)] = {"slots": slots[int(np.argmin(d))][valid].tolist(),
                            "distance_mm": float(d.min() * 1000),
                            "truth_distance_mm": float(d[0] * 1000)}
  return out


def _key(factor: str, horizon: int) -> str:
  return factor if horizon == 0 else f"{factor}, first {horizon} steps"


def summarize(rows: list[dict]) -> dict:
  """Per factor: top-1 per box and RMSE in slots over every box, with 95 % intervals from
  resampling tools (`metrics.bootstrap_interval`)."""
  labels = [np.asarray(r["labels"]) for r in rows]
  out = {}
  for name in [_key(f, h) for h in HORIZONS for f in FACTORS]:
    errors = [np.asarray(r[name]["slots"]) - lab for r, lab in zip(rows, labels)]
    pooled = lambda idx: np.concatenate([errors[i] for i in idx]).astype(float)
    top1 = lambda idx: 100 * float(np.mean(pooled(idx) == 0))
    rmse = lambda idx: float(np.sqrt(np.mean(pooled(idx) ** 2)))
    every = np.arange(len(rows))
    out[name] = {"top1": top1(every), "top1_ci95": metrics.bootstrap_interval(top1, len(rows)),
                 "rmse": rmse(every), "rmse_ci95": metrics.bootstrap_interval(rmse, len(rows)),
                 "median_error": float(np.median(pooled(every))),
                 "truth_picked_or_tied_%": 100 * float(np.mean(
                     [r[name]["truth_distance_mm"] <= r[name]["distance_mm"] + 1e-9
                      for r in rows])),
                 "distance_mm_median": float(np.median([r[name]["distance_mm"]
                                                        for r in rows]))}
  pool = lambda key, idx: np.concatenate([r["pool"][key] for r in (rows[i] for i in idx)])
  top1 = lambda idx: 100 * float(np.mean(pool("hit", idx)))
  rmse = lambda idx: float(np.sqrt(np.mean(pool("square_error", idx))))
  every = np.arange(len(rows))
  out["a candidate at random (expected)"] = {
      "top1": top1(every), "top1_ci95": metrics.bootstrap_interval(top1, len(rows)),
      "rmse": rmse(every), "rmse_ci95": metrics.bootstrap_interval(rmse, len(rows)),
      "median_error": 0.0, "truth_picked_or_tied_%": None, "distance_mm_median": None}
  return {"tools": len(rows), "boxes": int(sum(lab.size for lab in labels)), "rows": out}


def _cell(x: float, fmt: str) -> str:
  return "–" if x is None else format(x, fmt)


def markdown(s: dict, args, c: float) -> str:
  lines = ["# +Sample on the true boxes of tools, with candidates at the tool's mass", "",
           "```", s["command"], "```", "",
           f"{s['tools']} fresh tools (seed {args.seed}; {s['diverged']} left out: MuJoCo "
           f"diverged), {s['boxes']} boxes; {args.candidates} candidates a tool (the labels "
           f"and the labels moved by up to ±{args.radius} slots a box), MuJoCo C under the "
           f"tools' four pushes; {s['seconds']:.0f} s on this machine. The boxes weigh a "
           f"median {s['box_mass_ratio_median']:.2f}x the tool; c = {c:.3f} (median over "
           f"{args.calibrate_tools} tools of seed {args.calibrate_seed}).", "",
           "| candidates simulated at | top-1 per box (%) | RMSE (slots) | median pick − "
           "label (slots) | truth picked or tied (% of tools) | closest distance (mm, "
           "median) |", "|---|--:|--:|--:|--:|--:|"]
  for name, r in s["rows"].items():
    lines.append(f"| {name} | {r['top1']:.1f} [{r['top1_ci95'][0]:.1f}, "
                 f"{r['top1_ci95'][1]:.1f}] | {r['rmse']:.2f} [{r['rmse_ci95'][0]:.2f}, "
                 f"{r['rmse_ci95'][1]:.2f}] | {r['median_error']:+.0f} | "
                 f"{_cell(r['truth_picked_or_tied_%'], '.0f')} | "
                 f"{_cell(r['distance_mm_median'], '.2f')} |")
  return "\n".join(lines) + "\n"


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  define_study_flags("tool_mass_calibration", tools=100, seed=7, tools_help="Fresh test tools.")
  flags.DEFINE_integer("calibrate_seed", 8, "The calibration's seed.")
  flags.DEFINE_integer("calibrate_tools", 100, "Its tools.")
  flags.DEFINE_integer("candidates", 256, "Candidates a tool.")
  flags.DEFINE_integer("radius", 20, "Slots a label moves at most.")


def main(argv):
  del argv
  if FLAGS.tools < 1 or FLAGS.candidates < 2 or FLAGS.radius < 1:
    raise app.UsageError("--tools >= 1, --candidates >= 2 and --radius >= 1")
  t0 = time.perf_counter()
  c = calibration(FLAGS.calibrate_seed, FLAGS.calibrate_tools)
  rng = np.random.default_rng(FLAGS.seed)
  rows, diverged = over_tools(
      FLAGS.seed, FLAGS.tools,
      lambda tool: study_tool(tool, c, FLAGS.candidates, FLAGS.radius, rng))
  summary = {**summarize(rows), "diverged": diverged, "calibration": c,
             "box_mass_ratio_median": float(np.median([r["box_mass_ratio"] for r in rows])),
             "seconds": round(time.perf_counter() - t0, 1),
             "command": (f"python experiments/tool_mass_calibration/run.py --tools={FLAGS.tools} "
                         f"--seed={FLAGS.seed} --calibrate_seed={FLAGS.calibrate_seed} "
                         f"--calibrate_tools={FLAGS.calibrate_tools} "
                         f"--candidates={FLAGS.candidates} --radius={FLAGS.radius}")}
  write(FLAGS.out, summary, rows, markdown(summary, FLAGS, c), rows_key="tools_rows")


if __name__ == "__main__":
  define_flags()
  app.run(main)
