"""How much a tool's motion says about each part's density, beside how far boxes are from
the tool (issue 18's diagnosis: +Sample picks wrong densities even on the true boxes).

  python experiments/tool_identifiability/run.py --tools=120 --seed=2026

For fresh procedural tools (`dataset.tools`, normalised as the tools dataset does), with
MuJoCo C under the tools' four pushes (`tool_scene.simulate_tool`, `tool_pushes()`):
  * the model mismatch: the tool's trajectories against its true boxes' at their labels
    (`tool_generation.boxes_of_parts`, simulated by `ppdjax.simulate(backend="mujoco")`):
    the closest any box candidate can come, whatever its densities;
  * each part's sensitivity: the tool's own trajectories with that part's density times
    1.5 and divided by 1.5 (the other parts as they are), and for metal parts in the other
    mode of metal's two slot ranges (21-35 and 71-100, ×100 kg/m³);
  * the mismatch split: the tool's own shape with the boxes' mass properties
    (`simulate_tool(inertial=)`), against the tool (the mass properties' part) and against
    the boxes (the contact shape's part);
  * a part whose density change moves the tool less than the box mismatch cannot be read
    from the motion through boxes: the closest box trajectory is as likely to pick the
    wrong density as the right one.
Distance: the mean over pushes and steps of the object-frame origin's position error (mm).
Writes OUT/results.json, OUT/results.md and OUT/sensitivity.png.
"""

from __future__ import annotations

import collections
import os
import sys
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from absl import app, flags  # noqa: E402

import ppdjax  # noqa: E402
from ppdjax.conventions import density_to_slot, slot_to_density  # noqa: E402
from ppdjax.dataset import tool_scene  # noqa: E402
from ppdjax.dataset.meshes import normalize  # noqa: E402
from ppdjax.dataset.tool_generation import boxes_of_parts  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tool_studies.common import (define_study_flags, distance_mm, over_tools,  # noqa: E402
                                 write)

FLAGS = flags.FLAGS

FACTORS = (1.5, 1 / 1.5)


def other_metal_mode(slot: int) -> int:
  """The middle of metal's other slot range (0-based: 20-34 and 70-99)."""
  return 84 if slot <= 34 else 27


def simulated(parts, densities, **options):
  """`tool_scene.simulate_tool`, or None where MuJoCo diverges."""
  try:
    return tool_scene.simulate_tool(parts, densities, **options)
  except RuntimeError:
    return None


def study_tool(tool) -> dict | None:
  """One tool's mismatch and parts' sensitivities; None if MuJoCo diverges on it."""
  parts, _ = normalize(list(tool.parts))
  dens = tool.densities
  seen = simulated(parts, dens)
  if seen is None:
    return None
  off = lambda traj: None if traj is None else distance_mm(traj, seen)
  prims, _ = boxes_of_parts(parts, dens)
  try:
    boxes = np.asarray(ppdjax.simulate(prims, tool_scene.tool_pushes(), backend="mujoco"))
  except RuntimeError:  # rollout_mujoco.UnstableRollout: MuJoCo diverged on the boxes
    return None
  mass = np.asarray([p.volume for p in parts]) * dens
  out = {"category": tool.category, "mismatch_mm": distance_mm(boxes, seen),
         "moved_mm": distance_mm(seen, np.broadcast_to(seen[:, :1], seen.shape)), "parts": []}
  # the mismatch split: the tool's own shape with the boxes' mass, centre of mass and
  # inertia is off the tool by what the mass properties cost, and off the boxes by what
  # the contact shape (and where the pushes land) costs
  mp = ppdjax.mass_properties(prims)
  inertial = (float(mp.mass), np.asarray(mp.com, np.float64), np.asarray(mp.inertia, np.float64))
  out["box_mass_ratio"] = float(mp.mass / mass.sum())
  hybrid = simulated(parts, dens, inertial=inertial)
  out["mass_part_mm"] = off(hybrid)
  out["shape_part_mm"] = None if hybrid is None else distance_mm(hybrid, boxes)
  for i, (name, material) in enumerate(zip(tool.names, tool.materials)):
    with_part = lambda rho: off(simulated(parts, np.where(np.arange(len(dens)) == i, rho, dens)))
    changes = {f"x{factor:.3g}": with_part(dens[i] * factor) for factor in FACTORS}
    if material == "metal":
      changes["metal mode"] = with_part(
          slot_to_density(other_metal_mode(int(density_to_slot(dens[i])))))
    out["parts"].append({"name": name, "material": material,
                         "mass_fraction": float(mass[i] / mass.sum()), **changes})
  return out


def summarize(rows: list[dict]) -> dict:
  mismatch = np.asarray([r["mismatch_mm"] for r in rows])
  groups = collections.defaultdict(list)
  for r in rows:
    for p in r["parts"]:
      groups[(r["category"], p["name"], p["material"])].append({**p, "mismatch_mm":
                                                                r["mismatch_mm"]})
  table = []
  for (category, name, material), ps in sorted(groups.items()):
    up = np.asarray([p["x1.5"] for p in ps if p["x1.5"] is not None])
    swap = [p["metal mode"] for p in ps if p.get("metal mode") is not None]
    hidden = np.mean([p["x1.5"] < p["mismatch_mm"] for p in ps if p["x1.5"] is not None])
    table.append({"category": category, "part": name, "material": material, "parts": len(ps),
                  "mass_fraction": float(np.median([p["mass_fraction"] for p in ps])),
                  "x1.5_median_mm": float(np.median(up)),
                  "hidden_x1.5": float(hidden),
                  "metal_mode_median_mm": float(np.median(swap)) if swap else None,
                  "hidden_metal_mode": (float(np.mean([p["metal mode"] < p["mismatch_mm"]
                                                       for p in ps
                                                       if p.get("metal mode") is not None]))
                                        if swap else None)})
  every = [p for r in rows for p in r["parts"]]
  return {"tools": len(rows), "parts": len(every),
          "mismatch_mm": {"median": float(np.median(mismatch)),
                          "p90": float(np.percentile(mismatch, 90))},
          "moved_mm_median": float(np.median([r["moved_mm"] for r in rows])),
          "box_mass_ratio_median": float(np.median([r["box_mass_ratio"] for r in rows])),
          **{f"{k}_median": float(np.median([r[k] for r in rows if r[k] is not None]))
             for k in ("mass_part_mm", "shape_part_mm")},
          "by_category": {
              c: {"tools": sum(r["category"] == c for r in rows),
                  **{k: float(np.median([r[k] for r in rows
                                         if r["category"] == c and r[k] is not None]))
                     for k in ("box_mass_ratio", "mismatch_mm", "mass_part_mm",
                               "shape_part_mm")}}
              for c in sorted({r["category"] for r in rows})},
          "hidden_x1.5": float(np.mean([p["x1.5"] < r["mismatch_mm"] for r in rows
                                        for p in r["parts"] if p["x1.5"] is not None])),
          "by_part": table}


def plot(rows: list[dict], path: str) -> None:
  fig, ax = plt.subplots(figsize=(6.5, 4.5))
  for r in rows:
    for p in r["parts"]:
      if p["x1.5"] is None:
        continue
      hidden = p["x1.5"] < r["mismatch_mm"]
      ax.scatter(p["mass_fraction"], p["x1.5"], s=12, c="tab:red" if hidden else "tab:blue",
                 marker="x" if p["material"] == "metal" else "o", alpha=0.7)
  ax.set_xlabel("part's share of the tool's mass")
  ax.set_ylabel("trajectory change, density × 1.5 (mm)")
  ax.set_yscale("log")
  ax.set_title("red: less than the tool's own box mismatch; ×: metal parts", fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  define_study_flags("tool_identifiability", tools=120, seed=2026)


def main(argv):
  del argv
  t0 = time.perf_counter()
  rows, diverged = over_tools(FLAGS.seed, FLAGS.tools, study_tool)
  summary = {**summarize(rows), "diverged": diverged, "seed": FLAGS.seed,
             "seconds": round(time.perf_counter() - t0, 1),
             "command": f"python experiments/tool_identifiability/run.py --tools={FLAGS.tools} "
                        f"--seed={FLAGS.seed}"}
  os.makedirs(FLAGS.out, exist_ok=True)
  plot(rows, os.path.join(FLAGS.out, "sensitivity.png"))
  lines = [
      "# What a tool's motion says about each part's density", "", "```",
      summary["command"], "```", "",
      f"{summary['tools']} fresh tools (seed {FLAGS.seed}; {diverged} left out: MuJoCo "
      f"diverged), {summary['parts']} parts, MuJoCo C under the tools' four pushes "
      f"({tool_scene.TOOL_PUSH_FORCE:g} N). The tools move a median "
      f"{summary['moved_mm_median']:.1f} mm from rest (mean over steps). The true boxes at "
      f"their labels miss the tool's own trajectories by a median "
      f"{summary['mismatch_mm']['median']:.2f} mm (p90 {summary['mismatch_mm']['p90']:.2f}): "
      "no box candidate can come closer. A part is *hidden* when multiplying its density "
      "by 1.5 moves the tool less than that mismatch. Hidden overall: "
      f"**{100 * summary['hidden_x1.5']:.0f} %** of parts.", "",
      "The mismatch split: the tool's own shape simulated with its boxes' mass, centre of "
      "mass and inertia (the boxes weigh a median "
      f"{summary['box_mass_ratio_median']:.2f}x the tool) is a median "
      f"{summary['mass_part_mm_median']:.2f} mm off the tool (what the boxes' mass "
      f"properties cost) and {summary['shape_part_mm_median']:.2f} mm off the boxes (what "
      "their contact shape and where the pushes land cost). Medians by category:", "",
      "| category | tools | boxes / tool mass | box mismatch (mm) | mass properties' part (mm) "
      "| contact shape's part (mm) |", "|---|--:|--:|--:|--:|--:|"]
  for category, c in summary["by_category"].items():
    lines.append(f"| {category} | {c['tools']} | {c['box_mass_ratio']:.2f} | "
                 f"{c['mismatch_mm']:.2f} | {c['mass_part_mm']:.2f} | {c['shape_part_mm']:.2f} |")
  lines += [
      "",
      "| category | part | material | parts | mass share (median) | × 1.5: change (median mm) "
      "| hidden (× 1.5) | other metal mode: change (median mm) | hidden (metal mode) |",
      "|---|---|---|--:|--:|--:|--:|--:|--:|"]
  for t in summary["by_part"]:
    mm = "–" if t["metal_mode_median_mm"] is None else f"{t['metal_mode_median_mm']:.2f}"
    hm = "–" if t["hidden_metal_mode"] is None else f"{100 * t['hidden_metal_mode']:.0f} %"
    lines.append(f"| {t['category']} | {t['part']} | {t['material']} | {t['parts']} | "
                 f"{t['mass_fraction']:.2f} | {t['x1.5_median_mm']:.2f} | "
                 f"{100 * t['hidden_x1.5']:.0f} % | {mm} | {hm} |")
  lines += ["", "![sensitivity against mass share](sensitivity.png)", "",
            f"{summary['seconds']:.0f} s on the CPU."]
  write(FLAGS.out, summary, rows, "\n".join(lines) + "\n")


if __name__ == "__main__":
  define_flags()
  app.run(main)
