"""What the tool studies (`tool_identifiability`, `tool_mass_calibration`, `tool_voxel_body`,
`tool_resolution`, `tool_push_study`, `tool_early_motion`: each `experiments/<study>/run.py`)
share: their flags, the trajectory distance they report, the slot ranges they group parts
by, the boxes simulated under candidate densities, the loop over fresh tools that leaves out
those MuJoCo diverges on, and their output files."""

from __future__ import annotations

import json
import os

import numpy as np
from absl import flags
from tqdm import tqdm

import ppdjax
from ppdjax.dataset import tools


def slot_range(slot: int, material: str) -> str:
  """A part's group: its material, metal split into its two ranges (21-35, 71-100)."""
  if material == "metal":
    return "metal 71-100" if slot >= 70 else "metal 21-35"
  return material


def simulate_candidates(prims, densities: np.ndarray, pushes) -> np.ndarray:
  """(C, P, T, 7) trajectories of one tool's boxes `prims` (K slots) under each row of
  `densities` (C, K) kg/m³, by MuJoCo C."""
  count = len(densities)
  cands = prims.replace(**{f: np.broadcast_to(np.asarray(getattr(prims, f)),
                                              (count,) + np.shape(getattr(prims, f)))
                           for f in ("half_size", "pos", "quat", "valid")},
                        density=np.asarray(densities, np.float32))
  return np.asarray(ppdjax.simulate(cands, pushes, backend="mujoco"))


def distance_mm(a, b) -> float:
  """Mean over pushes and steps of the position error (mm)."""
  return float(np.linalg.norm(np.asarray(a)[..., :3] - np.asarray(b)[..., :3], axis=-1).mean()
               * 1000)


def define_study_flags(name: str, tools: int, seed: int, tools_help: str = "Fresh tools."):
  """The flags every tool study takes: --tools, --seed and --out (default
  experiments/results/NAME). A study defines its flags when it runs (in its `__main__`),
  not on import: the tests import the studies side by side, and absl refuses a flag
  defined twice."""
  flags.DEFINE_integer("tools", tools, tools_help)
  flags.DEFINE_integer("seed", seed, "Their seed.")
  flags.DEFINE_string("out", f"experiments/results/{name}", "Output folder.")


def over_tools(seed: int, count: int, study) -> tuple[list[dict], int]:
  """(rows, diverged): `study(tool)` for `count` tools of `seed`, a row each, except those
  it returns None for (MuJoCo diverged), counted; SystemExit if that is every tool."""
  rows, diverged = [], 0
  for tool in tqdm(tools.sample_tools(seed, count), desc="tools"):
    r = study(tool)
    if r is None:
      diverged += 1
    else:
      rows.append(r)
  if not rows:
    raise SystemExit("MuJoCo diverged on every tool")
  return rows, diverged


def write(out: str, summary: dict, rows: list[dict], text: str, rows_key: str = "rows"):
  """OUT/results.json (the summary and every tool's row under `rows_key`) and
  OUT/results.md (`text`, also printed)."""
  os.makedirs(out, exist_ok=True)
  with open(os.path.join(out, "results.json"), "w") as f:
    json.dump({**summary, rows_key: rows}, f, indent=1)
  with open(os.path.join(out, "results.md"), "w") as f:
    f.write(text)
  print(text)
