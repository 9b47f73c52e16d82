"""What the tool studies (`tool_identifiability.py`, `tool_mass_calibration.py`,
`tool_voxel_body.py`) share: the trajectory distance they report, the loop over fresh
tools that leaves out those MuJoCo diverges on, and their output files."""

from __future__ import annotations

import json
import os

import numpy as np
from tqdm import tqdm

from ppdjax.dataset import tools


def distance_mm(a, b) -> float:
  """Mean over pushes and steps of the position error (mm)."""
  return float(np.linalg.norm(np.asarray(a)[..., :3] - np.asarray(b)[..., :3], axis=-1).mean()
               * 1000)


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
