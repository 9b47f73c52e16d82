"""Speed of the tools' ground-truth boxes (`mesh_boxes.boxes_of_parts`), the largest share
of making a tool sample, with the split search's pruning against fitting every cut.

  python experiments/benchmarks/bench_tool_boxes.py --tools=40 --seed=5

For fresh procedural tools (normalised as the dataset does), in one process, one after
the other on the same surface samples:
  * peer, "every cut": `fit_point_boxes(prune=False)`, each of the 42 plane cuts of a box
    fitted with two minimum oriented boxes (the code before 2026-11-27);
  * "pruned": `fit_point_boxes(prune=True)` (the default), a cut fitted only if its two
    halves' convex hulls leave room for the saving a split must make.
Both must give the same boxes, bit for bit; the script stops if they differ. It prints
and writes the seconds per tool and the ratio, and how long a whole tool sample of the
tools preset (`tool_generation.tool_samples`: 4 configurations) takes now.
"""

from __future__ import annotations

import json
import os
import platform
import time

import numpy as np
from absl import app, flags

from ppdjax.dataset import meshes, mesh_boxes, tool_generation, tools

flags.DEFINE_integer("tools", 40, "Fresh tools.", lower_bound=1)
flags.DEFINE_integer("seed", 5, "Their seed.")
flags.DEFINE_integer("samples", 8, "Whole tool samples to time.", lower_bound=0)
flags.DEFINE_string("out", "experiments/results/bench_tool_boxes.json", "Results JSON.")
FLAGS = flags.FLAGS


def main(argv):
  del argv
  seconds = {"every cut": 0.0, "pruned": 0.0}
  boxes_made = 0
  for tool in tools.sample_tools(FLAGS.seed, FLAGS.tools):
    parts, _ = meshes.normalize(list(tool.parts))
    points, part = meshes.surface_samples(parts, mesh_boxes.SAMPLES)
    volume = sum(abs(p.volume) for p in parts)
    out = {}
    for name, prune in (("every cut", False), ("pruned", True)):
      t = time.perf_counter()
      out[name] = mesh_boxes.fit_point_boxes(points, part, volume, prune=prune)
      seconds[name] += time.perf_counter() - t
    same = len(out["every cut"]) == len(out["pruned"]) and all(
        np.array_equal(x, y) for a, b in zip(out["every cut"], out["pruned"])
        for x, y in zip(a, b))
    if not same:
      raise SystemExit(f"tool {tool.category} of seed {FLAGS.seed}: the pruned boxes differ")
    boxes_made += len(out["pruned"])
  t = time.perf_counter()
  for i in range(FLAGS.samples):
    tool_generation.tool_samples(FLAGS.seed, i, 224, 256, configs=4)
  sample_s = (time.perf_counter() - t) / max(FLAGS.samples, 1)
  per_tool = {k: v / FLAGS.tools for k, v in seconds.items()}
  result = {"tools": FLAGS.tools, "seed": FLAGS.seed, "boxes": boxes_made,
            "seconds_per_tool": per_tool,
            "speedup": per_tool["every cut"] / per_tool["pruned"],
            "tool_sample_seconds": sample_s if FLAGS.samples else None,
            "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "command": f"python experiments/benchmarks/bench_tool_boxes.py --tools={FLAGS.tools} "
                       f"--seed={FLAGS.seed} --samples={FLAGS.samples}"}
  print(f"{FLAGS.tools} tools, {boxes_made} boxes, the same with and without pruning")
  print(f"  every cut (peer): {per_tool['every cut']:.3f} s a tool")
  print(f"  pruned:           {per_tool['pruned']:.3f} s a tool  "
        f"({result['speedup']:.2f}x the peer)")
  if FLAGS.samples:
    print(f"  a whole tool sample (4 configurations, 224² image): {sample_s:.2f} s")
  os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
  with open(FLAGS.out, "w") as f:
    json.dump(result, f, indent=1)


if __name__ == "__main__":
  app.run(main)
