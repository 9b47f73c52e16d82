"""How much of a tool's part densities does the motion just after a push hold? (issue 18, CPU)

  python experiments/tool_early_motion/run.py --tools=60 --seed=2033 --configs=40 --steps=4

+Sample's closest whole trajectory reads the parts' densities of these tools poorly even
with the tool's own body (`tool_push_study --readers=own`: RMSE 7.9 slots). But what a
push does at once is set by the mass properties alone: Δv = J/m and Δω = I⁻¹ (r − c) × J
for an impulse J at r, before friction and contacts take over. This study asks how
precisely those first velocities pin the densities, with the geometry held fixed.

For each fresh tool of two or more parts (normalised as the dataset does), `--configs`
density configurations are drawn as the dataset draws them (`tools.with_new_slots`) and
simulated for `--steps` + 1 steps under the paper's four pushes (MuJoCo C, the dataset's
1e3 N). Features: each push's linear velocity (with its inverse speed) and, in the second
reader, its angular velocity, between recorded poses 0..steps (`ppdjax.nn.motion.early_motion`,
without the compression; pose 0 is the one after the push's step). Within the tool, a ridge regression from the standardised
features to every part's log density is scored leaving one configuration out. The error
is |log ρ̂ − log ρ| (0.01 is 1 %); "spread" predicts each configuration by the tool's
mean (what the geometry and materials alone give). Writes OUT/results.{json,md}.
"""

from __future__ import annotations

import os
import sys

import jax.numpy as jnp
import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.conventions import density_to_slot
from ppdjax.dataset import meshes, tool_scene, tools
from ppdjax.nn.motion import decompress, early_motion

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tool_studies.common import define_study_flags, over_tools, write  # noqa: E402

FLAGS = flags.FLAGS

READERS = ("spread", "linear velocity", "linear and angular velocity")
RIDGE = 1e-2


def velocities(traj_PTx7: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
  """(linear (P·steps·3,), angular (P·steps·3,)) velocities over recorded steps 1..steps,
  undoing `early_motion`'s compression."""
  x = decompress(early_motion(jnp.asarray(traj_PTx7[None], jnp.float32), steps))
  x = x.reshape(traj_PTx7.shape[0], steps, 6)
  return x[..., :3].ravel(), x[..., 3:].ravel()


def loo_errors(features: np.ndarray, targets: np.ndarray) -> np.ndarray:
  """(C, parts) signed error (prediction − target) of a ridge regression leaving each of the C rows out in turn."""
  x = (features - features.mean(0)) / (features.std(0) + 1e-9)
  x = np.c_[x, np.ones(len(x))]
  out = []
  for i in range(len(x)):
    keep = np.arange(len(x)) != i
    a = x[keep]
    coef = np.linalg.solve(a.T @ a + RIDGE * np.eye(a.shape[1]), a.T @ targets[keep])
    out.append(x[i] @ coef - targets[i])
  return np.asarray(out)


def study_tool(tool, configs: int, steps: int, rng) -> dict | None:
  """The three readers' leave-one-out errors over `configs` configurations of `tool`;
  None for one-part tools and where MuJoCo diverges."""
  if len(tool.parts) < 2:
    return None
  parts, _ = meshes.normalize(list(tool.parts))
  lin, ang, logs, slots = [], [], [], []
  for _ in range(configs):
    cfg = tools.with_new_slots(tool, rng)
    try:
      traj = tool_scene.simulate_tool(parts, cfg.densities, steps=steps + 1)
    except RuntimeError:
      return None
    v, w = velocities(traj, steps)
    speed = np.linalg.norm(v.reshape(-1, 3), axis=-1)
    lin.append(np.r_[v, 1 / np.maximum(speed, 1e-6)])
    ang.append(w)
    logs.append(np.log(cfg.densities))
    slots.append(cfg.slots)
  lin, ang, logs = np.asarray(lin), np.asarray(ang), np.asarray(logs)
  errors = {"spread": logs.mean(0) - logs,
            "linear velocity": loo_errors(lin, logs),
            "linear and angular velocity": loo_errors(np.c_[lin, ang], logs)}
  return {"category": tool.category, "materials": list(tool.materials),
          **{k: e.tolist() for k, e in errors.items()},
          "slot_error_linear_and_angular": np.abs(
              density_to_slot(np.exp(logs + errors["linear and angular velocity"]))
              - np.asarray(slots)).tolist()}


def summarize(rows: list[dict]) -> dict:
  """Per reader: median and mean |log-density error| over every part of every
  configuration, with 95 % intervals from resampling tools."""
  out = {}
  for reader in READERS:
    per_tool = [np.abs(np.ravel(r[reader])) for r in rows]
    pooled = lambda idx: np.concatenate([per_tool[i] for i in idx])  # noqa: E731
    median = lambda idx: float(np.median(pooled(idx)))  # noqa: E731
    mean = lambda idx: float(np.mean(pooled(idx)))  # noqa: E731
    every = np.arange(len(rows))
    out[reader] = {"median": median(every),
                   "median_ci95": metrics.bootstrap_interval(median, len(rows)),
                   "mean": mean(every), "mean_ci95": metrics.bootstrap_interval(mean, len(rows)),
                   "p90": float(np.percentile(pooled(every), 90))}
  return out


def markdown(summary: dict, args, diverged: int) -> str:
  lines = [
      "# The motion just after a push, within one tool's configurations", "",
      "```", f"python experiments/tool_early_motion/run.py --tools={args.tools} --seed={args.seed} "
      f"--configs={args.configs} --steps={args.steps}", "```", "",
      f"{summary['tools']} tools of two or more parts (of {args.tools} drawn; {diverged} "
      f"left out: one part or MuJoCo diverged), {args.configs} density configurations each, "
      f"velocities over the {args.steps} steps after each of the four pushes (1e3 N); "
      "ridge regression within each tool, leave one configuration out; |log ρ̂ − log ρ| "
      "over every part (0.01 is 1 %), 95 % intervals over tools.", "",
      "| reader | median | mean | p90 |", "|---|--:|--:|--:|"]
  for reader in READERS:
    r = summary["readers"][reader]
    lines.append(f"| {reader} | {r['median']:.3f} [{r['median_ci95'][0]:.3f}, "
                 f"{r['median_ci95'][1]:.3f}] | {r['mean']:.3f} [{r['mean_ci95'][0]:.3f}, "
                 f"{r['mean_ci95'][1]:.3f}] | {r['p90']:.3f} |")
  s = summary["slots_linear_and_angular"]
  lines += ["", f"In slots (linear and angular): {s['exact']:.1f} % of parts exact, "
            f"{s['within_2']:.1f} % within 2, RMSE {s['rmse']:.2f}.", ""]
  return "\n".join(lines)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  define_study_flags("tool_early_motion", tools=60, seed=2033)
  flags.DEFINE_integer("configs", 40, "Configurations a tool.")
  flags.DEFINE_integer("steps", 4, "Recorded steps after the push.")


def main(argv):
  del argv
  if FLAGS.tools < 1 or FLAGS.configs < 4 or FLAGS.steps < 1:
    raise app.UsageError("--tools >= 1, --configs >= 4 and --steps >= 1")
  rng = np.random.default_rng(FLAGS.seed)
  rows, diverged = over_tools(FLAGS.seed, FLAGS.tools,
                              lambda t: study_tool(t, FLAGS.configs, FLAGS.steps, rng))
  slot_err = np.concatenate([np.ravel(r["slot_error_linear_and_angular"]) for r in rows])
  summary = {"tools": len(rows), "configs": FLAGS.configs, "steps": FLAGS.steps,
             "readers": summarize(rows),
             "slots_linear_and_angular": {
                 "exact": 100 * float(np.mean(slot_err == 0)),
                 "within_2": 100 * float(np.mean(slot_err <= 2)),
                 "rmse": float(np.sqrt(np.mean(slot_err.astype(float) ** 2)))}}
  write(FLAGS.out, summary, rows, markdown(summary, FLAGS, diverged), rows_key="tools_rows")


if __name__ == "__main__":
  define_flags()
  app.run(main)
