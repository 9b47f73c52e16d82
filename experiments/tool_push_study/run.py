"""Which push magnitude lets a tool's motion pick its densities? (issue 18, a CPU study)

  python experiments/tool_push_study/run.py --tools=120 --seed=2029 --forces=300,1000,3000

`tool_resolution` found that at the dataset's 1e3 N a tool's response to a small
density change is partly a jump, and proportional at 300 N. This study asks the global
question +Sample and the network face: among candidate density assignments, does the
closest trajectory have the closest densities?

For fresh procedural tools (normalised as the dataset does), the observation is the
tool's own motion under the paper's four push directions at each magnitude (MuJoCo C,
`tool_scene.simulate_tool`). The candidates are `--candidates` density assignments, each
part's slot drawn uniformly within its material's range (as `tools.with_new_slots` draws
a configuration), the same for every magnitude; the truth is not added. Each candidate is
simulated twice:
  * with the tool's own parts ("own shape"): the ceiling, no model mismatch;
  * with the tool's true boxes (`mesh_boxes.boxes_of_parts`), each box at the density of
    the part it covers: what +Sample simulates on right boxes.
The candidate whose trajectory is closest (`metrics.trajectory_distance`) is picked and
its parts' slots are scored against the truth: RMSE in slots and the share within 5
slots, beside a candidate drawn at random (expected) and the candidate closest in slots
(the best the pool holds). "Explained" is (random - pick) / (random - best) of the mean
squared error: 0 is a random pick, 1 the pool's best. Writes OUT/results.{json,md}.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.conventions import slot_to_density
from ppdjax.dataset import meshes, tool_scene
from ppdjax.dataset.materials import material_slots
from ppdjax.dataset.mesh_boxes import boxes_of_parts

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tool_studies.common import (define_study_flags, over_tools,  # noqa: E402
                                 simulate_candidates, slot_range, write)

FLAGS = flags.FLAGS

READERS = ("own shape", "true boxes")
NEAR_SLOTS = 5
WITHIN = (0, 2, 4)  # the picks' shares of parts this many slots or fewer off (0: exact)


def _distances(simulate, candidates: np.ndarray, seen: np.ndarray) -> np.ndarray:
  """(C,) trajectory distance (m) of each candidate's simulation; inf where it diverges."""
  out = np.full(len(candidates), np.inf)
  for i, slots in enumerate(candidates):
    try:
      out[i] = float(metrics.trajectory_distance(simulate(slots), seen))
    except RuntimeError:
      pass
  return out


def draw_candidates(tool, count: int, rng) -> np.ndarray:
  """(count, parts) slots, each part's drawn uniformly within its material's range."""
  return np.stack([rng.choice(material_slots(m), count) for m in tool.materials], -1)


def study_tool(tool, forces: list[float], candidates: np.ndarray,
               readers: tuple[str, ...] = READERS) -> dict | None:
  """The picks among `candidates` (C, parts) at each magnitude by each of `readers`; None
  where MuJoCo diverges on the tool itself."""
  parts, _ = meshes.normalize(list(tool.parts))
  prims, owner = boxes_of_parts(parts, tool.densities)
  truth = np.asarray(tool.slots)
  square = ((candidates - truth) ** 2).astype(float)  # (C, parts)
  best = candidates[int(np.argmin(square.sum(-1)))]
  out = {"category": tool.category, "slots": truth.tolist(),
         "ranges": [slot_range(s, m) for s, m in zip(tool.slots, tool.materials)],
         "random_square_error": square.mean(0).tolist(), "best": best.tolist()}
  boxed = np.asarray(owner) >= 0
  for force in forces:
    pushes = tool_scene.tool_pushes(force)
    try:
      seen = tool_scene.simulate_tool(parts, tool.densities, pushes)
    except RuntimeError:
      return None
    distances = {}
    if "own shape" in readers:
      distances["own shape"] = _distances(
          lambda s: tool_scene.simulate_tool(parts, slot_to_density(s), pushes), candidates, seen)
    if "true boxes" in readers:
      dens = np.where(boxed, slot_to_density(candidates[:, np.maximum(owner, 0)]),
                      np.asarray(prims.density)[None])
      distances["true boxes"] = np.asarray(metrics.trajectory_distance(
          simulate_candidates(prims, dens, pushes), seen))
    moved = np.linalg.norm(seen[:, -1, :3] - seen[:, 0, :3], axis=-1)
    out[f"{force:g}"] = {"motion_mm": float(np.sqrt((moved ** 2).mean()) * 1000),
                         "diverged_candidates": int(np.isinf(
                             distances.get("own shape", np.zeros(1))).sum()),
                         **{reader: candidates[int(np.argmin(d))].tolist()
                            for reader, d in distances.items()}}
  return out


def summarize(rows: list[dict], forces: list[float], readers: tuple[str, ...] = READERS) -> dict:
  """Per magnitude and reader: RMSE (slots) and the share within NEAR_SLOTS, with 95 %
  intervals from resampling tools, the shares within WITHIN slots; the same by slot range
  for the picks."""
  truth = [np.asarray(r["slots"]) for r in rows]
  ranges = np.concatenate([r["ranges"] for r in rows])
  every = np.arange(len(rows))

  def scored(errors: list[np.ndarray]) -> dict:
    pooled = lambda idx: np.concatenate([errors[i] for i in idx]).astype(float)  # noqa: E731
    rmse = lambda idx: float(np.sqrt(np.mean(pooled(idx) ** 2)))  # noqa: E731
    near = lambda idx: 100 * float(np.mean(np.abs(pooled(idx)) <= NEAR_SLOTS))  # noqa: E731
    flat = pooled(every)
    return {"rmse": rmse(every), "rmse_ci95": metrics.bootstrap_interval(rmse, len(rows)),
            "near": near(every), "near_ci95": metrics.bootstrap_interval(near, len(rows)),
            "within": {str(k): 100 * float(np.mean(np.abs(flat) <= k)) for k in WITHIN},
            "rmse_by_range": {g: float(np.sqrt(np.mean(flat[ranges == g] ** 2)))
                              for g in sorted(set(ranges))}}

  random_mse = float(np.mean(np.concatenate([r["random_square_error"] for r in rows])))
  best = scored([np.asarray(r["best"]) - t for r, t in zip(rows, truth)])
  out = {"random_rmse": float(np.sqrt(random_mse)), "best": best, "forces": {}}
  for force in forces:
    key = f"{force:g}"
    per = {"motion_mm_median": float(np.median([r[key]["motion_mm"] for r in rows])),
           "diverged_candidates": int(sum(r[key]["diverged_candidates"] for r in rows))}
    for reader in readers:
      s = scored([np.asarray(r[key][reader]) - t for r, t in zip(rows, truth)])
      s["explained"] = ((random_mse - s["rmse"] ** 2)
                        / max(random_mse - best["rmse"] ** 2, 1e-12))
      per[reader] = s
    out["forces"][key] = per
  return out


def markdown(s: dict, args) -> str:
  groups = sorted(s["best"]["rmse_by_range"])
  lines = ["# Which push magnitude lets a tool's motion pick its densities", "", "```",
           s["command"], "```", "",
           f"{s['tools']} fresh tools (seed {args.seed}; {s['diverged']} left out: MuJoCo "
           f"diverged on the tool at some magnitude), {s['parts']} parts; {args.candidates} "
           "candidates a tool, each part's slot drawn within its material's range, the same "
           f"at every magnitude; {s['seconds']:.0f} s on this machine (2 CPU cores). A "
           f"candidate at random: RMSE {s['random_rmse']:.1f} slots; the pool's best: "
           f"{s['best']['rmse']:.1f}.", "",
           "| push (N) | tool moves (RMS mm, median) | picked with | RMSE (slots) | within "
           f"{NEAR_SLOTS} slots (%) | explained | exact / within 2 / within 4 (% of parts) | "
           + " | ".join(groups) + " |",
           "|--:|--:|---|--:|--:|--:|--:|" + "--:|" * len(groups)]
  within = lambda r: " / ".join(f"{r['within'][str(k)]:.1f}" for k in WITHIN)  # noqa: E731
  for key, per in s["forces"].items():
    for reader in [r for r in READERS if r in per]:
      r = per[reader]
      lines.append(
          f"| {key} | {per['motion_mm_median']:.0f} | {reader} | {r['rmse']:.1f} "
          f"[{r['rmse_ci95'][0]:.1f}, {r['rmse_ci95'][1]:.1f}] | {r['near']:.0f} "
          f"[{r['near_ci95'][0]:.0f}, {r['near_ci95'][1]:.0f}] | {r['explained']:.2f} | "
          f"{within(r)} | " + " | ".join(f"{r['rmse_by_range'][g]:.1f}" for g in groups) + " |")
  b = s["best"]
  lines.append(f"| – | – | the pool's best | {b['rmse']:.1f} | {b['near']:.0f} | 1 | "
               f"{within(b)} | " + " | ".join(f"{b['rmse_by_range'][g]:.1f}" for g in groups)
               + " |")
  lines += ["", "The last columns: RMSE (slots) of the picks by the true slot's range."]
  return "\n".join(lines) + "\n"


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  define_study_flags("tool_push_study", tools=120, seed=2029)
  flags.DEFINE_string("forces", "300,1000,3000", "Push magnitudes (N), comma-separated.")
  flags.DEFINE_integer("candidates", 64, "Candidates a tool.")
  flags.DEFINE_string("readers", "own,boxes", "Which bodies simulate the candidates: own (the "
                      "tool's parts), boxes (its true boxes), or both.")


def main(argv):
  del argv
  forces = [float(f) for f in FLAGS.forces.split(",") if f]
  names = {"own": "own shape", "boxes": "true boxes"}
  wanted = [r for r in FLAGS.readers.split(",") if r]
  if FLAGS.tools < 1 or FLAGS.candidates < 2 or not forces or min(forces) <= 0:
    raise app.UsageError("--tools >= 1, --candidates >= 2 and positive --forces")
  if not wanted or set(wanted) - set(names):
    raise app.UsageError(f"--readers: a comma-separated subset of {sorted(names)}, got "
                         f"{FLAGS.readers!r}")
  readers = tuple(names[r] for r in names if r in wanted)
  t0 = time.perf_counter()
  rng = np.random.default_rng(FLAGS.seed)
  rows, diverged = over_tools(FLAGS.seed, FLAGS.tools,
                              lambda tool: study_tool(tool, forces, draw_candidates(
                                  tool, FLAGS.candidates, rng), readers))
  summary = {**summarize(rows, forces, readers), "tools": len(rows), "diverged": diverged,
             "parts": int(sum(len(r["slots"]) for r in rows)),
             "seconds": round(time.perf_counter() - t0, 1),
             "command": (f"python experiments/tool_push_study/run.py --tools={FLAGS.tools} "
                         f"--seed={FLAGS.seed} --forces={FLAGS.forces} "
                         f"--candidates={FLAGS.candidates}"
                         + (f" --readers={FLAGS.readers}" if FLAGS.readers != "own,boxes"
                            else ""))}
  write(FLAGS.out, summary, rows, markdown(summary, FLAGS), rows_key="tools_rows")


if __name__ == "__main__":
  define_flags()
  app.run(main)
