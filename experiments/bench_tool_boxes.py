"""Speed of the tools' ground-truth boxes (`mesh_boxes.boxes_of_parts`), the largest share
of making a tool sample, with the split search's pruning against fitting every cut.

  python experiments/bench_tool_boxes.py --tools=40 --seed=5

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

import argparse
import json
import os
import platform
import time

import numpy as np

from ppdjax.dataset import meshes, mesh_boxes, tool_generation, tools


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--tools", type=int, default=40, help="fresh tools")
  parser.add_argument("--seed", type=int, default=5, help="their seed")
  parser.add_argument("--samples", type=int, default=8, help="whole tool samples to time")
  parser.add_argument("--out", default="experiments/results/bench_tool_boxes.json")
  args = parser.parse_args()
  if args.tools < 1 or args.samples < 0:
    parser.error("--tools >= 1 and --samples >= 0")
  seconds = {"every cut": 0.0, "pruned": 0.0}
  boxes_made = 0
  for tool in tools.sample_tools(args.seed, args.tools):
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
      raise SystemExit(f"tool {tool.category} of seed {args.seed}: the pruned boxes differ")
    boxes_made += len(out["pruned"])
  t = time.perf_counter()
  for i in range(args.samples):
    tool_generation.tool_samples(args.seed, i, 224, 256, configs=4)
  sample_s = (time.perf_counter() - t) / max(args.samples, 1)
  per_tool = {k: v / args.tools for k, v in seconds.items()}
  result = {"tools": args.tools, "seed": args.seed, "boxes": boxes_made,
            "seconds_per_tool": per_tool,
            "speedup": per_tool["every cut"] / per_tool["pruned"],
            "tool_sample_seconds": sample_s if args.samples else None,
            "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "command": f"python experiments/bench_tool_boxes.py --tools={args.tools} "
                       f"--seed={args.seed} --samples={args.samples}"}
  print(f"{args.tools} tools, {boxes_made} boxes, the same with and without pruning")
  print(f"  every cut (peer): {per_tool['every cut']:.3f} s a tool")
  print(f"  pruned:           {per_tool['pruned']:.3f} s a tool  "
        f"({result['speedup']:.2f}x the peer)")
  if args.samples:
    print(f"  a whole tool sample (4 configurations, 224² image): {sample_s:.2f} s")
  os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
  with open(args.out, "w") as f:
    json.dump(result, f, indent=1)


if __name__ == "__main__":
  main()
