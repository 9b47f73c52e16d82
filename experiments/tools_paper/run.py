"""The paper protocol's two free choices, measured: the recipe's box cost and the push force.

  python experiments/tools_paper/run.py --out=experiments/results/tools_paper_choices

1. Box counts of the paper's recipe (`mesh_boxes.fit_point_boxes` from one box around the
   whole tool) at several box costs, on TOOLS tools (every category alike).
2. Under the paper's four push directions at several forces, the tools' boxes (as
   `dataset.tool_paper` makes them, two configurations each) simulated by MuJoCo C and by
   the box-plane engine: how fast they start, how far they go, how many leave the scene,
   and whether an engine fails.
"""

from __future__ import annotations

import collections
import json
import os
import time

import numpy as np
from absl import app, flags

from ppdjax import mass_properties, primitives, simulate
from ppdjax.dataset import mesh_boxes, tool_paper, tools
from ppdjax.dataset.meshes import normalize, surface_samples
from ppdjax.report.provenance import write_provenance
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import ESCAPE_DISTANCE

flags.DEFINE_string("out", "experiments/results/tools_paper_choices", "Results folder.")
flags.DEFINE_integer("tools", 24, "Tools for the box counts (3 of each category).")
flags.DEFINE_integer("sim_tools", 32, "Tools for the push forces.")
flags.DEFINE_list("costs", ["0.15", "0.3", "0.5", "1.0"], "Box costs.")
flags.DEFINE_list("forces", ["1e5", "3e4", "1e4", "3e3"], "Push forces (N).")
flags.DEFINE_list("backends", ["mujoco", "box_plane"], "Engines.")
FLAGS = flags.FLAGS
SEED = 5  # never a dataset's seed


def box_counts() -> dict:
  data = []
  for i in range(FLAGS.tools):
    tool = tools.sample_tool(SEED, i, tools.CATEGORIES[i % len(tools.CATEGORIES)])
    parts, _ = normalize(list(tool.parts))
    points, _ = surface_samples(parts, tool_paper.SAMPLES)
    data.append((tool.category, points, sum(abs(p.volume) for p in parts)))
  out = {}
  for cost in map(float, FLAGS.costs):
    t0, by_category, ratio = time.perf_counter(), collections.defaultdict(list), []
    for category, points, volume in data:
      boxes = mesh_boxes.fit_point_boxes(points, np.zeros(len(points), int), volume,
                                         tool_paper.MAX_BOXES, cost)
      by_category[category].append(len(boxes))
      ratio.append(sum(8 * np.prod(b[2]) for b in boxes) / volume)
    counts = collections.Counter(c for v in by_category.values() for c in v)
    out[str(cost)] = {"counts": {str(k): counts[k] for k in sorted(counts)},
                      "by_category": dict(by_category),
                      "box_volume_over_mesh_median": float(np.median(ratio)),
                      "seconds_per_tool": (time.perf_counter() - t0) / len(data)}
    print(cost, out[str(cost)], flush=True)
  return out


def forces() -> dict:
  rows = [r for i in range(FLAGS.sim_tools) for r in tool_paper.tool_samples(SEED, i, 32, 2)]
  prims = primitives.Primitives(*[np.stack([r[f] for r in rows]) for f in primitives.FIELDS])
  mass = np.asarray(mass_properties(prims).mass)
  out = {"objects": len(rows), "mass_kg_p10_p50_p90": np.percentile(mass, [10, 50, 90]).tolist()}
  for backend in FLAGS.backends:
    for force in map(float, FLAGS.forces):
      key = f"{backend} {force:g} N"
      try:
        traj = np.asarray(simulate(prims, default_pushes(force), backend=backend))
      except (RuntimeError, FloatingPointError) as e:  # an engine that failed says so
        out[key] = {"failed": str(e)[:300]}
        print(key, out[key], flush=True)
        continue
      speed = np.linalg.norm(traj[:, :, 1, :3] - traj[:, :, 0, :3], axis=-1) * 300
      travel = np.linalg.norm(traj[:, :, -1, :3] - traj[:, :, 0, :3], axis=-1)
      left = np.linalg.norm(traj[:, :, -1, :3], axis=-1) > 0.9 * ESCAPE_DISTANCE
      out[key] = {"speed_p10_p50_p90": np.percentile(speed, [10, 50, 90]).tolist(),
                  "travel_p10_p50_p90_max": np.percentile(travel, [10, 50, 90, 100]).tolist(),
                  "rollouts": int(left.size), "left_the_scene": int(left.sum())}
      print(key, out[key], flush=True)
  return out


def main(argv):
  del argv
  os.makedirs(FLAGS.out, exist_ok=True)
  result = {"box_cost": box_counts(), "push_force": forces()}
  path = os.path.join(FLAGS.out, "results.json")
  with open(path, "w") as f:
    json.dump(result, f, indent=1)
  write_provenance(path, command="python experiments/tools_paper/run.py --out=" + FLAGS.out)


if __name__ == "__main__":
  app.run(main)
