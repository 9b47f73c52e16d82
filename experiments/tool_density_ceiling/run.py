"""How well a tool's exact mass properties give its true boxes' densities (CPU).

  python experiments/tool_density_ceiling/run.py \
      --records=experiments/results/tools_runs/eval_full/records \
      --out=experiments/results/tool_density_ceiling

A push moves a rigid body through its contact shape and its mass properties: the mass,
centre of mass and inertia, ten numbers, the only part of the motion the densities
change. On the test split's tools (rebuilt from the preset's seed, every configuration
checked against the evaluation's records) this study scores readers given those ten
numbers **exactly**, beside the shipped model's own guesses (the records' PPD row):

- **raw**: the true boxes' densities whose moments (mass, first moments, second moments
  about the object's origin) come closest, non-negative least squares;
- **corrected**: each reading times a density correction (label / raw reading) learned on
  tools of another seed by category, box count and box position: a box around a cylinder,
  wedge or bent blade holds more than its part, and misplaces its mass;
- **corrected, material known**: the fit itself bounded to each box's material range (its
  columns divided by their corrections), then the nearest slot of the material.

Each reader is scored on every box, and apart on boxes of parts holding under `HIDDEN[0]`
of the tool's mass, whose density barely moves the tool. The **hidden-part floor** is the
split's RMSE if those boxes are read at their material's mean slot and every other box
exactly. Per-box top-1 is the exact slot; "within 2" and "within 5" stand in for a top-5
and a top-10 (a point reading has no ranking). Intervals: 95 % bootstrap over tools.
Writes OUT/results.md and OUT/results.json.
"""

from __future__ import annotations

import json
import os
import sys

import jax
import numpy as np
from absl import app, flags
from scipy.optimize import lsq_linear
from tqdm import tqdm

from ppdjax import metrics, primitives
from ppdjax.configs import tools as tools_preset
from ppdjax.conventions import MAX_DENSITY, density_to_slot, slot_to_density
from ppdjax.dataset import materials, mesh_boxes, tool_scene, tools
from ppdjax.dataset.meshes import normalize
from ppdjax.dataset.tool_generation import density_variants
from ppdjax.eval import partial
from ppdjax.sim.mass import mass_properties

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from tools_by_category.run import test_tools  # noqa: E402

FLAGS = flags.FLAGS

LENGTH = 0.25  # m in the object frame: scales first and second moments to the mass's size
HIDDEN = (0.01, 0.02, 0.03)  # shares of the tool's mass under which a part is called hidden
READERS = ("raw", "corrected", "corrected, material known")
_box_properties = jax.jit(mass_properties)


def tool_moments(mass: float, com: np.ndarray, inertia: np.ndarray) -> np.ndarray:
  """(10,) mass, first moment / LENGTH, second moment about the origin (upper triangle) /
  LENGTH^2, of a body of this mass, centre of mass and inertia about it."""
  spread = np.trace(inertia) / 2 * np.eye(3) - inertia  # integral of r r^T about the com
  second = spread + mass * np.outer(com, com)
  return np.concatenate([[mass], mass * np.asarray(com) / LENGTH,
                         second[np.triu_indices(3)] / LENGTH ** 2])


def box_moments(prims: primitives.Primitives) -> np.ndarray:
  """(10, k) tool_moments of each valid box alone at unit density (`sim.mass`)."""
  k = int(np.asarray(prims.valid).sum())
  alone = jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (k,) + np.shape(x)), prims)
  alone = alone.replace(density=np.eye(k, len(prims.valid), dtype=np.float32))
  props = _box_properties(alone)
  return np.stack([tool_moments(float(m), np.asarray(c, np.float64), np.asarray(i, np.float64))
                   for m, c, i in zip(props.mass, props.com, props.inertia)], 1)


def read_densities(columns: np.ndarray, target: np.ndarray, lower=0.0,
                   upper=np.inf) -> np.ndarray:
  """(k,) densities, within [lower, upper], whose boxes' moments (columns (10, k), one per
  unit density) come closest to `target` (10,) in least squares."""
  return lsq_linear(columns, target, bounds=(lower, upper), method="bvls").x


def tool_rows(seed: int, index: int, configs: int) -> list[dict]:
  """One dict per density configuration of tool `index` (`density_variants`, attempt 0):
  its boxes' true slots, the raw reading, each box's part's share of the mass, the part's
  name and material, and the boxes' moment columns."""
  tool = tools.sample_tool(seed, index)
  parts, _ = normalize(list(tool.parts))
  prims, owner = mesh_boxes.boxes_of_parts(parts, tool.densities)
  k = int(np.asarray(prims.valid).sum())
  owner = owner[:k]
  columns = box_moments(prims)
  volumes = np.asarray([abs(p.volume) for p in parts])
  rows = []
  for v in density_variants(tool, seed, index, configs):
    target = tool_moments(*tool_scene.mass_properties(parts, v.densities))
    part_mass = volumes * v.densities
    rows.append({"category": tool.category, "tool": index, "count": k, "columns": columns,
                 "target": target, "slot": density_to_slot(v.densities[owner]),
                 "raw": read_densities(columns, target),
                 "share": part_mass[owner] / part_mass.sum(),
                 "part": [tool.names[o] for o in owner],
                 "material": [tool.materials[o] for o in owner]})
  return rows


def _keys(r: dict, j: int) -> tuple:
  return ((r["category"], r["count"], j), (r["category"],), ("all",))


def corrections(rows: list[dict]) -> dict:
  """Median label / raw reading by (category, box count, box position), by category and
  overall ("all"), over readings of at least the lowest slot's density (a box the fit
  left empty says nothing about its correction)."""
  ratios: dict = {}
  for r in rows:
    for j, (s, est) in enumerate(zip(r["slot"], r["raw"])):
      if est >= slot_to_density(0):
        for key in _keys(r, j):
          ratios.setdefault(key, []).append(np.log(slot_to_density(s) / est))
  return {k: float(np.exp(np.median(v))) for k, v in ratios.items()}


def box_corrections(r: dict, table: dict) -> np.ndarray:
  """(k,) the most specific correction `table` holds for each of r's boxes."""
  return np.asarray([next(table[key] for key in _keys(r, j) if key in table)
                     for j in range(r["count"])])


def nearest_in_material(material: str, density: float) -> float:
  """The density of the slot of `material` nearest to `density`."""
  slots = materials.material_slots(material)
  return float(slot_to_density(slots[np.argmin(np.abs(slots - density_to_slot(density)))]))


def read_in_material(r: dict, correction: np.ndarray) -> np.ndarray:
  """(k,) densities fitted within each box's material range, the columns divided by their
  corrections, each then moved to its material's nearest slot."""
  lo = [slot_to_density(materials.material_slots(m).min()) for m in r["material"]]
  hi = [slot_to_density(materials.material_slots(m).max()) for m in r["material"]]
  fit = read_densities(r["columns"] / correction, r["target"], np.asarray(lo), np.asarray(hi))
  return np.asarray([nearest_in_material(m, d) for m, d in zip(r["material"], fit)])


def readings(rows: list[dict], table: dict) -> dict:
  """{reader: per-box slot errors} over rows, READERS order."""
  out = {name: [] for name in READERS}
  for r in rows:
    c = box_corrections(r, table)
    for name, d in zip(READERS, (r["raw"], r["raw"] * c, read_in_material(r, c))):
      out[name].append(density_to_slot(np.clip(d, slot_to_density(0), MAX_DENSITY)) - r["slot"])
  return {k: np.concatenate(v) for k, v in out.items()}


def scores(err: np.ndarray, tool_of_box: np.ndarray) -> dict:
  """Top-1, within 2 and 5 (%), RMSE (slots) of per-box errors, with intervals over tools."""
  stats = {"top1": lambda e: 100 * np.mean(e == 0),
           "within2": lambda e: 100 * np.mean(np.abs(e) <= 2),
           "within5": lambda e: 100 * np.mean(np.abs(e) <= 5),
           "rmse": lambda e: float(np.sqrt(np.mean(e.astype(np.float64) ** 2)))}
  out = {"boxes": int(len(err))}
  for name, f in stats.items():
    out[name] = float(f(err))
    out[name + "_ci"] = list(metrics.bootstrap_interval(lambda i, f=f: f(err[i]), len(err),
                                                        groups=tool_of_box))
  return out


def floor(rows: list[dict], threshold: float) -> dict:
  """The split's RMSE if boxes of parts under `threshold` of the tool's mass are read at
  their material's mean slot and every other box exactly; which parts those are."""
  sq, names = [], {}
  for r in rows:
    for s, share, part, m in zip(r["slot"], r["share"], r["part"], r["material"]):
      hidden = share < threshold
      sq.append((s - materials.material_slots(m).mean()) ** 2 if hidden else 0.0)
      if hidden:
        key = f"{r['category']} {part} ({m})"
        names[key] = names.get(key, 0) + 1
  return {"threshold": threshold, "hidden_boxes_pct": 100 * sum(names.values()) / len(sq),
          "rmse_floor": float(np.sqrt(np.mean(sq))), "hidden": names}


def network_errors(rec: dict, rows: list[dict]) -> tuple[np.ndarray, list[int]]:
  """(per-box errors of the records' PPD guesses, positions of configurations whose
  records' true slots or box counts differ from the rebuilt ones)."""
  guess, slot = np.asarray(rec[("guess", "PPD")]), np.asarray(rec[("true_slot",)])
  valid = np.asarray(rec[("true_valid",)])
  bad = [i for i, r in enumerate(rows)
         if valid[i].sum() != r["count"] or not np.array_equal(slot[i, :r["count"]], r["slot"])]
  err = np.concatenate([guess[i, :r["count"]] - slot[i, :r["count"]]
                        for i, r in enumerate(rows)])
  return err, bad


def markdown(out: dict) -> str:
  """results.md: the readers' table and the floors."""
  fmt = lambda s, k: f"{s[k]:.1f} [{s[k + '_ci'][0]:.1f}, {s[k + '_ci'][1]:.1f}]"
  lines = ["# Exact mass properties and the tools' box densities (Table 3's test split)", "",
           "```", out["command"], "```", "",
           f"{out['tools']} test tools x {out['configs']} configurations, {out['boxes']} "
           f"boxes ({out['left_out']} configurations left out: records differ from the "
           f"rebuilt tool); corrections from {out['calibrate_tools']} tools of seed "
           f"{out['calibrate_seed']}; hidden: parts under {100 * HIDDEN[0]:.0f} % of the "
           "tool's mass. Intervals: 95 % bootstrap over tools.", "",
           "| reader | boxes | top-1 (%) | within 2 slots (%) | within 5 (%) | RMSE (slots) |",
           "|---|--:|--:|--:|--:|--:|"]
  for name, s in out["readers"].items():
    lines.append(f"| {name} | {s['boxes']} | {fmt(s, 'top1')} | {fmt(s, 'within2')} | "
                 f"{fmt(s, 'within5')} | {fmt(s, 'rmse')} |")
  lines += ["", "| parts under this share of the tool's mass | boxes (%) | RMSE floor "
            "(slots) | which |", "|--:|--:|--:|---|"]
  for f in out["floors"]:
    which = ", ".join(f"{k} {v}" for k, v in sorted(f["hidden"].items()))
    lines.append(f"| {100 * f['threshold']:.0f} % | {f['hidden_boxes_pct']:.1f} | "
                 f"{f['rmse_floor']:.2f} | {which} |")
  return "\n".join(lines) + "\n"


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_string("records", None, "The tools evaluation's kept records.", required=True)
  flags.DEFINE_string("out", None, "Output folder.", required=True)
  flags.DEFINE_integer("tools", 0, "The first N test tools (0: all).")
  flags.DEFINE_integer("calibrate_seed", 8, "Seed of the tools the corrections are learned on.")
  flags.DEFINE_integer("calibrate_tools", 100, "Those tools.")
  flags.DEFINE_integer("calibrate_configs", 4, "Density configurations a calibration tool.")
  flags.DEFINE_string("size", "paper", "The tools preset's size of the data.")


def main(argv):
  """Rebuilds the test tools, checks them against the records, scores and writes."""
  del argv
  if not os.path.exists(FLAGS.records):
    raise SystemExit(f"not found: {FLAGS.records}")
  preset = tools_preset.get_config(FLAGS.size)
  data, configs = preset.data, int(preset.data.configs_per_tool)
  ids = test_tools(data.num_tools, data.split_fractions)
  rec = partial.saved_records(FLAGS.records)
  if len(rec[("blocks",)]) != len(ids) * configs:
    raise SystemExit(f"{len(rec[('blocks',)])} records, but the preset's test split has "
                     f"{len(ids) * configs} objects: records of another dataset")
  ids = ids[:FLAGS.tools] if FLAGS.tools else ids
  rows = [r for i in tqdm(ids, desc="test tools") for r in tool_rows(preset.seed, int(i),
                                                                     configs)]
  calib = [r for i in tqdm(range(FLAGS.calibrate_tools), desc="calibration tools")
           for r in tool_rows(FLAGS.calibrate_seed, i, FLAGS.calibrate_configs)]
  net_err, bad = network_errors({k: np.asarray(v)[:len(rows)] for k, v in rec.items()}, rows)
  keep = np.ones(len(rows), bool)
  keep[bad] = False
  keep_box = np.concatenate([[k] * r["count"] for k, r in zip(keep, rows)])
  kept = [r for r, k in zip(rows, keep) if k]
  table = corrections(calib)
  errors = {"the shipped model, PPD (full)": net_err[keep_box], **readings(kept, table)}
  tool = np.concatenate([[r["tool"]] * r["count"] for r in kept])
  seen = np.concatenate([r["share"] for r in kept]) >= HIDDEN[0]
  readers = {}
  for name, err in errors.items():
    readers[name] = scores(err, tool)
    readers[f"{name}: hidden boxes"] = scores(err[~seen], tool[~seen])
    readers[f"{name}: other boxes"] = scores(err[seen], tool[seen])
  command = (f"python experiments/tool_density_ceiling/run.py --records={FLAGS.records} "
             f"--out={FLAGS.out}" + (f" --tools={FLAGS.tools}" if FLAGS.tools else ""))
  out = {"command": command, "tools": len(ids), "configs": configs,
         "boxes": int(keep_box.sum()), "left_out": len(bad),
         "calibrate_seed": FLAGS.calibrate_seed, "calibrate_tools": FLAGS.calibrate_tools,
         "readers": readers, "floors": [floor(kept, t) for t in HIDDEN],
         "corrections": {"/".join(map(str, k)): v for k, v in table.items()}}
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump(out, f, indent=1)
  md = markdown(out)
  with open(os.path.join(FLAGS.out, "results.md"), "w") as f:
    f.write(md)
  print(md)


if __name__ == "__main__":
  define_flags()
  app.run(main)
