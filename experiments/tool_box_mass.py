"""How much more a tool's true boxes weigh than the tool, with the parts' densities as
labels: what a trajectory fit on the true boxes must undo by lowering the densities.

  python experiments/tool_box_mass.py --tools=100 --seed=7 \
      --out=experiments/results/tools_order_study/box_mass.json

Tools of a seed (`tools.sample_tool`), normalised; true boxes and their labels
(`mesh_boxes.boxes_of_parts`: a box takes the density of the part it covers most). Per
tool: the tool's mass (the parts' exact volumes and densities) and the boxes' mass (box
volumes times their labels), and the ratio. Then per box the label's slot beside the slot
of the label scaled by tool mass / box mass (the densities that give the boxes the tool's
mass, split as the labels split it): their RMSE in slots is how far a method that matches
the total mass on the true boxes lands from the labels, before any other error. With
--calibrate_seed, the same after a calibration: every box's density divided by the median
box mass / tool mass of that seed's tools (what a trajectory fit could undo on average).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
from tqdm.auto import tqdm

from ppdjax.conventions import density_to_slot
from ppdjax.dataset import meshes, tools
from ppdjax.dataset.mesh_boxes import boxes_of_parts
from ppdjax.metrics import bootstrap_interval


def tool_masses(tool: tools.Tool) -> dict:
  """The tool's and its true boxes' masses (kg) and the boxes' labels (kg/m^3)."""
  parts, _ = meshes.normalize(list(tool.parts))
  prims, _ = boxes_of_parts(parts, tool.densities)
  valid = np.asarray(prims.valid)
  box_volume = np.prod(2 * np.asarray(prims.half_size)[valid], -1)
  labels = np.asarray(prims.density)[valid]
  mass = float(sum(abs(p.volume) * d for p, d in zip(parts, tool.densities)))
  return {"category": tool.category, "mass": mass,
          "box_mass": float((box_volume * labels).sum()), "labels": labels.tolist()}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--tools", type=int, default=100)
  parser.add_argument("--seed", type=int, default=7)
  parser.add_argument("--calibrate_seed", type=int, default=None)
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  masses = lambda seed: [tool_masses(tools.sample_tool(seed, i))
                         for i in tqdm(range(args.tools), desc=f"tools of seed {seed}")]
  rows = masses(args.seed)
  ratio = np.array([r["box_mass"] / r["mass"] for r in rows])
  labels = [np.array(r["labels"]) for r in rows]
  box_tool = np.concatenate([np.full(len(lab), i) for i, lab in enumerate(labels)])

  def slot_errors(scale):  # labels / scale: what gives the boxes the tool's mass
    return np.concatenate([density_to_slot(lab * scale / q) - density_to_slot(lab)
                           for lab, q in zip(labels, ratio)]).astype(np.float64)

  def rmse_of(err):
    return lambda idx: float(np.sqrt(np.mean(np.concatenate([err[box_tool == i]
                                                              for i in idx]) ** 2)))
  err = slot_errors(1.0)
  rmse = rmse_of(err)
  command = f"python experiments/tool_box_mass.py --tools={args.tools} --seed={args.seed}"
  extra = {}
  if args.calibrate_seed is not None:
    command += f" --calibrate_seed={args.calibrate_seed}"
    scale = float(np.median([r["box_mass"] / r["mass"] for r in masses(args.calibrate_seed)]))
    calibrated = rmse_of(slot_errors(scale))
    extra = {"calibration": {"seed": args.calibrate_seed, "box_mass_over_tool_mass": scale,
                             "mass_matched_rmse_slots": calibrated(np.arange(len(rows))),
                             "mass_matched_rmse_ci95": list(bootstrap_interval(
                                 calibrated, len(rows))),
                             "slot_shift_median": float(np.median(slot_errors(scale)))}}
  out = {"command": command,
         "tools": args.tools, "boxes": int(len(err)),
         "box_mass_over_tool_mass": {"median": float(np.median(ratio)),
                                     "p10": float(np.percentile(ratio, 10)),
                                     "p90": float(np.percentile(ratio, 90))},
         "by_category": {c: float(np.median([q for q, r in zip(ratio, rows)
                                             if r["category"] == c]))
                         for c in sorted({r["category"] for r in rows})},
         "mass_matched_rmse_slots": rmse(np.arange(len(rows))),
         "mass_matched_rmse_ci95": list(bootstrap_interval(rmse, len(rows))),
         "mass_matched_slot_shift_median": float(np.median(err)), **extra}
  print(json.dumps(out, indent=1))
  if args.out:
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
      json.dump(out, f, indent=1)


if __name__ == "__main__":
  main()
