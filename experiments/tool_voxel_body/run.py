"""Would candidates shaped like a tool's voxels move more like the tool than its boxes do?
(issue 18: through its true boxes, the closest trajectory reads a tool's densities no
better than at random, `tool_mass_calibration`.)

  python experiments/tool_voxel_body/run.py --tools=60 --seed=7

For fresh procedural tools (normalised as the dataset does), MuJoCo C under the tools' four
pushes: the tool's own trajectories against those of
  * its true boxes at their labels (`mesh_boxes.boxes_of_parts`; what +Sample simulates);
  * its voxel body: the 32^3 voxels the model sees (`meshes.voxelize_parts`), merged into
    boxes along z within each column and part, each voxel with the density of its part
    (what a candidate could be built from at test time, with the boxes' densities);
  * the voxel body at the tool's mass (every density times tool mass / body mass: what a
    known total mass would add).
Distance: the mean over pushes and steps of the object-frame origin's position error
(mm), as `tool_identifiability`. Writes OUT/results.json and OUT/results.md.
"""

from __future__ import annotations

import collections
import os
import sys
import time

import numpy as np
import trimesh
from absl import app, flags

import ppdjax
from ppdjax.dataset import meshes, tool_scene
from ppdjax.dataset.mesh_boxes import boxes_of_parts

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tool_studies.common import (define_study_flags, distance_mm, over_tools,  # noqa: E402
                                 write)

FLAGS = flags.FLAGS

BODIES = ("true boxes", "voxel body", "voxel body at the tool's mass")


def voxel_columns(per_part: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
  """(part, lo corner, hi corner) boxes in the normalised frame covering every occupied
  voxel once: each voxel goes to the first part that holds it, and runs of one part's
  voxels along z within an (x, y) column become one box."""
  owner = np.where(per_part.any(0), per_part.argmax(0), -1)
  r = owner.shape[0]
  out = []
  for i, j in zip(*np.nonzero((owner >= 0).any(-1))):
    column, k = owner[i, j], 0
    while k < r:
      if column[k] < 0:
        k += 1
        continue
      start, part = k, column[k]
      while k < r and column[k] == part:
        k += 1
      lo = np.array([i, j, start]) / r - 0.5
      hi = np.array([i + 1, j + 1, k]) / r - 0.5
      out.append((int(part), lo, hi))
  return out


def voxel_body(parts, densities) -> tuple[list, np.ndarray]:
  """(box meshes, their densities): the tool's voxel body (`voxel_columns`)."""
  _, per_part = meshes.voxelize_parts(parts)
  boxes = voxel_columns(per_part)
  body = [trimesh.creation.box(extents=hi - lo,
                               transform=trimesh.transformations.translation_matrix(
                                   (lo + hi) / 2)) for _, lo, hi in boxes]
  return body, np.asarray([densities[p] for p, _, _ in boxes], np.float64)


def study_tool(tool) -> dict | None:
  parts, _ = meshes.normalize(list(tool.parts))
  dens = np.asarray(tool.densities, np.float64)
  try:
    seen = tool_scene.simulate_tool(parts, dens)
    body, body_dens = voxel_body(parts, dens)
    voxels = tool_scene.simulate_tool(body, body_dens)
    tool_mass = float(sum(abs(p.volume) * d for p, d in zip(parts, dens)))
    body_mass = float(sum(b.volume * d for b, d in zip(body, body_dens)))
    matched = tool_scene.simulate_tool(body, body_dens * tool_mass / body_mass)
  except RuntimeError:
    return None
  prims, _ = boxes_of_parts(parts, dens)
  try:
    boxes = np.asarray(ppdjax.simulate(prims, tool_scene.tool_pushes(), backend="mujoco"))
  except RuntimeError:  # rollout_mujoco.UnstableRollout: MuJoCo diverged on the boxes
    return None
  return {"category": tool.category, "voxel_boxes": len(body),
          "moved_mm": distance_mm(seen, np.broadcast_to(seen[:, :1], seen.shape)),
          "box_mass_ratio": float(ppdjax.mass_properties(prims).mass) / tool_mass,
          "voxel_mass_ratio": body_mass / tool_mass,
          **{name: distance_mm(traj, seen)
             for name, traj in zip(BODIES, (boxes, voxels, matched))}}


def summarize(rows: list[dict]) -> dict:
  med = lambda key, rs: float(np.median([r[key] for r in rs]))
  by = collections.defaultdict(list)
  for r in rows:
    by[r["category"]].append(r)
  keys = BODIES + ("moved_mm", "box_mass_ratio", "voxel_mass_ratio", "voxel_boxes")
  return {"tools": len(rows), "median": {k: med(k, rows) for k in keys},
          "p90": {k: float(np.percentile([r[k] for r in rows], 90)) for k in BODIES},
          "voxels_closer_%": 100 * float(np.mean([r["voxel body"] < r["true boxes"]
                                                   for r in rows])),
          "by_category": {c: {"tools": len(rs), **{k: med(k, rs) for k in keys}}
                          for c, rs in sorted(by.items())}}


def markdown(s: dict) -> str:
  m = s["median"]
  lines = ["# A tool's voxel body against its boxes, under the tools' pushes", "", "```",
           s["command"], "```", "",
           f"{s['tools']} fresh tools ({s['diverged']} left out: MuJoCo diverged), MuJoCo "
           f"C, {s['seconds']:.0f} s on this machine. The tools move a median "
           f"{m['moved_mm']:.1f} mm from rest (mean over steps). The voxel body is a median "
           f"{m['voxel_boxes']:.0f} boxes and weighs {m['voxel_mass_ratio']:.2f}x the tool "
           f"(the true boxes {m['box_mass_ratio']:.2f}x).", "",
           "| simulated body | distance to the tool's trajectories, median (mm) | p90 |",
           "|---|--:|--:|"]
  for name in BODIES:
    lines.append(f"| {name} | {m[name]:.2f} | {s['p90'][name]:.2f} |")
  lines += ["", f"The voxel body is closer than the true boxes for "
            f"{s['voxels_closer_%']:.0f} % of tools.", "",
            "| category | tools | true boxes | voxel body | at the tool's mass | voxel body / "
            "tool mass |", "|---|--:|--:|--:|--:|--:|"]
  for c, r in s["by_category"].items():
    lines.append(f"| {c} | {r['tools']} | {r['true boxes']:.2f} | {r['voxel body']:.2f} | "
                 f"{r[BODIES[2]]:.2f} | {r['voxel_mass_ratio']:.2f} |")
  return "\n".join(lines) + "\n"


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  define_study_flags("tool_voxel_body", tools=60, seed=7)


def main(argv):
  del argv
  if FLAGS.tools < 1:
    raise app.UsageError("--tools must be >= 1")
  t0 = time.perf_counter()
  rows, diverged = over_tools(FLAGS.seed, FLAGS.tools, study_tool)
  s = {**summarize(rows), "diverged": diverged, "seconds": round(time.perf_counter() - t0, 1),
       "command": f"python experiments/tool_voxel_body/run.py --tools={FLAGS.tools} "
                  f"--seed={FLAGS.seed}"}
  write(FLAGS.out, s, rows, markdown(s))


if __name__ == "__main__":
  define_flags()
  app.run(main)
