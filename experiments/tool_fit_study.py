"""How well boxes fitted to a tool's 32^3 voxels match its ground-truth boxes.

  python experiments/tool_fit_study.py --tools=64 --seed=11 --out=experiments/results/tool_fit_study

Tools of a seed (`tools.sample_tool`), normalised; truth: `mesh_boxes.boxes_of_parts`;
fit: `ppdjax.fit_boxes(voxels)` (no network start) at each --box_costs; shape F1 (IoU >
0.5) with a 95 % bootstrap interval over tools, and how thin the true boxes are in voxels
(what limits any fit to 32^3 voxels).
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np
from tqdm.auto import tqdm

import ppdjax
from ppdjax import metrics, primitives
from ppdjax.dataset import meshes, tools
from ppdjax.dataset.mesh_boxes import boxes_of_parts


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--tools", type=int, default=64)
  parser.add_argument("--seed", type=int, default=11)
  parser.add_argument("--box_costs", default="0.01,0.05,0.2")
  parser.add_argument("--out", default="experiments/results/tool_fit_study")
  args = parser.parse_args()
  vox, true = [], []
  for i in tqdm(range(args.tools), desc="tools"):
    tool = tools.sample_tool(args.seed, i)
    parts, _ = meshes.normalize(list(tool.parts))
    vox.append(meshes.voxelize_parts(parts)[0])
    true.append(boxes_of_parts(parts, tool.densities)[0])
  vox, true = np.stack(vox), primitives.stack(true)
  half = np.asarray(true.half_size)[np.asarray(true.valid)]
  thickness = 2 * half.min(1) * ppdjax.conventions.VOXEL_RESOLUTION
  rows = []
  for cost in [float(c) for c in args.box_costs.split(",")]:
    fit = ppdjax.fit_boxes(vox, box_cost=cost)
    c = jax.tree.map(np.asarray, metrics.shape_counts(fit, jax.tree.map(jax.numpy.asarray, true)))
    f1 = lambda idx, c=c: metrics.f1_from_counts(c["matched"][idx], c["predicted"][idx],  # noqa: E731
                                                 c["true"][idx])
    rows.append({"box_cost": cost, "f1": f1(np.arange(args.tools)),
                 "f1_ci95": metrics.bootstrap_interval(f1, args.tools),
                 "boxes_fitted": int(c["predicted"].sum()), "boxes_true": int(c["true"].sum()),
                 "matched": int(c["matched"].sum())})
  out = {"tools": args.tools, "seed": args.seed, "rows": rows,
         "true_box_thickness_voxels": {"median": float(np.median(thickness)),
                                       "below_1": float((thickness < 1).mean()),
                                       "below_2": float((thickness < 2).mean())}}
  os.makedirs(args.out, exist_ok=True)
  with open(os.path.join(args.out, "results.json"), "w") as f:
    json.dump(out, f, indent=1)
  t = out["true_box_thickness_voxels"]
  lines = ["# Boxes fitted to tools' voxels", "",
           f"`python experiments/tool_fit_study.py --tools={args.tools} --seed={args.seed}`", "",
           f"{args.tools} tools, {len(thickness)} true boxes: thinnest side median "
           f"{t['median']:.2f} voxels; {100 * t['below_1']:.0f} % thinner than one voxel, "
           f"{100 * t['below_2']:.0f} % than two.", "",
           "| box_cost | shape F1 [95 %] | boxes fitted / true | matched |", "|--:|--:|--:|--:|"]
  lines += [f"| {r['box_cost']} | {r['f1']:.1f} [{r['f1_ci95'][0]:.1f}, {r['f1_ci95'][1]:.1f}] | "
            f"{r['boxes_fitted']} / {r['boxes_true']} | {r['matched']} |" for r in rows]
  with open(os.path.join(args.out, "results.md"), "w") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


if __name__ == "__main__":
  main()
