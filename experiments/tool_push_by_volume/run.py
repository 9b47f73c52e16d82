"""How fast the realistic tools start and how far they go, pushed alike or by volume.

  python experiments/tool_push_by_volume/run.py --out=experiments/results/tool_push_by_volume

TOOLS tools of seed SEED (never a dataset's) under the plausible labels
(`tools.sample_plausible_tool`), each under CONFIGS density configurations, simulated by
MuJoCo C under the paper's four push directions: (a) every tool at 1e3 N (the earlier
labels' "fixed"); (b) `tool_scene.push_force_for(F, volume, "by_volume")` at F = 2e3, 5e3
and 1e4 N.
Prints and writes the start speed (the centre's, just after the push) and the distance
travelled in 256 steps, their percentiles and the share of rollouts moving < 1 cm, with
the tools' mass range, and the share starting slower than SLOW (under 1.7 mm between two
frames of a 30 fps camera, about a tracker's error: not measurable).
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import app, flags

from ppdjax.conventions import TIMESTEP
from ppdjax.dataset import tool_generation, tool_scene, tools
from ppdjax.dataset.meshes import normalize

flags.DEFINE_string("out", "experiments/results/tool_push_by_volume", "Results folder.")
flags.DEFINE_integer("tools", 64, "Tools.")
flags.DEFINE_integer("configs", 2, "Density configurations a tool.")
FLAGS = flags.FLAGS
SEED = 11  # never a dataset's seed
SLOW = 0.05  # m/s
MODES = {"fixed 1e3 N": (1e3, "fixed"), "by volume, 2e3 N at 3 litres": (2e3, "by_volume"),
         "by volume, 5e3 N at 3 litres": (5e3, "by_volume"),
         "by volume, 1e4 N at 3 litres": (1e4, "by_volume")}


def summary(x: np.ndarray) -> dict:
  return {k: float(v) for k, v in zip(("p1", "p10", "p50", "p90", "p99"),
                                      np.percentile(x, [1, 10, 50, 90, 99]))}


def main(_):
  speeds = {m: [] for m in MODES}
  travel = {m: [] for m in MODES}
  masses, diverged = [], {m: 0 for m in MODES}
  for i in range(FLAGS.tools):
    tool = tools.sample_plausible_tool(SEED, i)
    parts, _ = normalize(list(tool.parts))
    volume = sum(abs(p.volume) for p in parts)
    for variant in tool_generation.density_variants(tool, SEED, i, FLAGS.configs):
      masses.append(float(np.dot([abs(p.volume) for p in parts], variant.densities)))
      for mode, (force, rule) in MODES.items():
        pushes = tool_scene.tool_pushes(tool_scene.push_force_for(force, volume, rule))
        try:
          traj = tool_scene.simulate_tool(parts, variant.densities, pushes)
        except RuntimeError:
          diverged[mode] += 1
          continue
        pos = traj[..., :3]
        speeds[mode] += list(np.linalg.norm(pos[:, 3] - pos[:, 1], axis=-1) / (2 * TIMESTEP))
        travel[mode] += list(np.linalg.norm(pos[:, -1] - pos[:, 0], axis=-1))
  out = {"tools": FLAGS.tools, "configs": FLAGS.configs, "seed": SEED,
         "mass_kg": summary(np.asarray(masses)), "modes": {}}
  for mode in MODES:
    s, t = np.asarray(speeds[mode]), np.asarray(travel[mode])
    out["modes"][mode] = {"start_speed_m_s": summary(s), "travel_m": summary(t),
                          "still_fraction": 100.0 * float(np.mean(t < 0.01)),
                          "slow_fraction": 100.0 * float(np.mean(s < SLOW)),
                          "rollouts": int(len(s)), "diverged_configs": diverged[mode]}
  print(json.dumps(out, indent=1))
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump(out, f, indent=1)


if __name__ == "__main__":
  app.run(main)
