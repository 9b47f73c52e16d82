"""What Table 3's density columns allow on the procedural tools, whatever the model (CPU).

  python experiments/tool_density_ceiling.py \
      --records=experiments/results/tools_runs/eval_full/records \
      --out=experiments/results/tool_density_ceiling

A push moves a rigid body through its contact shape and its mass properties: the mass,
centre of mass and inertia, ten numbers. On the test split's tools (rebuilt from the
preset's seed, every configuration checked against the evaluation's records) this study
scores three readers beside the shipped model's own guesses (the records' PPD row):

- **Oracle mass properties through the true boxes.** Each configuration's exact ten
  numbers (what the motion could reveal at best, `tool_scene.mass_properties`) are
  explained by the true boxes' densities: non-negative least squares on the moment
  equations (mass, first moments, second moments about the object's origin). Raw, and
  with the boxes' fill calibrated on tools of another seed by category, box count and box
  position (a box is a cylinder's or a wedge's bounding box, not the part).
- **The hidden-part floor.** A box whose part holds under `--hidden` of the tool's mass
  moves the tool less than the geometry's own uncertainty; if such a box is read no better
  than its material's prior (its slots' mean, the material known), no reader's RMSE over
  the whole split can go below sqrt(sum of those priors' variances / boxes).

Per-box top-1 is the exact slot; "within 2" and "within 5" are what a top-5 and a top-10
centred on a point estimate can hold at most. Intervals: 95 % bootstrap over tools.
Writes OUT/results.md and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
from scipy.optimize import nnls
from tqdm import tqdm

from ppdjax import metrics, primitives
from ppdjax.configs import tools as tools_preset
from ppdjax.conventions import density_to_slot, slot_to_density
from ppdjax.dataset import materials, mesh_boxes, tool_scene, tools
from ppdjax.dataset.meshes import normalize
from ppdjax.infer import partial

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from tools_by_category import test_tools  # pylint: disable=wrong-import-position

LENGTH = 0.25  # metres: scales first and second moments to the mass's magnitude
HIDDEN = (0.01, 0.02, 0.03)  # mass fractions under which a part is called hidden


def moment_vector(mass: float, first: np.ndarray, second: np.ndarray) -> np.ndarray:
  """(10,) mass, first moment (3,) / LENGTH, second moment about the origin (upper
  triangle, 6) / LENGTH^2."""
  iu = np.triu_indices(3)
  return np.concatenate([[mass], first / LENGTH, second[iu] / LENGTH ** 2])


def tool_moments(mass: float, com: np.ndarray, inertia: np.ndarray) -> np.ndarray:
  """moment_vector of a body from its mass, centre of mass and inertia about it."""
  spread = np.trace(inertia) / 2 * np.eye(3) - inertia  # integral of r r^T about the com
  return moment_vector(mass, mass * com, spread + mass * np.outer(com, com))


def box_moments(prims: primitives.Primitives) -> np.ndarray:
  """(10, k) moment vectors of the valid boxes at unit density."""
  cols = []
  for half, pos, quat, valid in zip(*(np.asarray(getattr(prims, f), np.float64) for f in
                                      ("half_size", "pos", "quat", "valid"))):
    if not valid:
      continue
    rot = np.asarray(primitives.quat_to_mat(quat.astype(np.float32)), np.float64)
    vol = 8 * np.prod(half)
    spread = vol * rot @ np.diag(half ** 2 / 3) @ rot.T
    cols.append(moment_vector(vol, vol * pos, spread + vol * np.outer(pos, pos)))
  return np.stack(cols, 1)


def read_densities(columns: np.ndarray, target: np.ndarray) -> np.ndarray:
  """(k,) non-negative densities whose boxes' moments come closest to `target`'s,
  relative to its mass."""
  rho, _ = nnls(columns / target[0], target / target[0])
  return rho


def tool_rows(seed: int, index: int, configs: int) -> list[dict]:
  """One dict per configuration of tool `index` (as `tool_generation.tool_samples` makes
  them, attempt 0): its boxes' true slots, the oracle reading, each box's part's share of
  the mass, the box's material."""
  tool = tools.sample_tool(seed, index)
  parts, _ = normalize(list(tool.parts))
  prims, owner = mesh_boxes.boxes_of_parts(parts, tool.densities)
  k = int(np.asarray(prims.valid).sum())
  owner = owner[:k]
  columns = box_moments(prims)
  volumes = np.asarray([abs(p.volume) for p in parts])
  variants = [tool] + [tools.with_new_slots(tool, np.random.default_rng([seed, index, c]))
                       for c in range(1, configs)]
  rows = []
  for v in variants:
    target = tool_moments(*tool_scene.mass_properties(parts, v.densities))
    part_mass = volumes * v.densities
    rows.append({"category": tool.category, "tool": index, "count": k,
                 "slot": density_to_slot(v.densities[owner]),
                 "oracle": read_densities(columns, target),
                 "share": part_mass[owner] / part_mass.sum(),
                 "material": [tool.materials[o] for o in owner]})
  return rows


def fill_factors(rows: list[dict]) -> dict:
  """Median label / oracle density by (category, box count, box position), by category,
  and overall ("all")."""
  ratios: dict = {}
  for r in rows:
    for j, (s, est) in enumerate(zip(r["slot"], r["oracle"])):
      lr = np.log((s + 1) * 100.0 / max(est, 1.0))
      for key in ((r["category"], r["count"], j), (r["category"],), ("all",)):
        ratios.setdefault(key, []).append(lr)
  return {k: float(np.exp(np.median(v))) for k, v in ratios.items()}


def calibrated(r: dict, factors: dict) -> np.ndarray:
  """r's oracle densities times the most specific fill factor known."""
  out = []
  for j, est in enumerate(r["oracle"]):
    for key in ((r["category"], r["count"], j), (r["category"],), ("all",)):
      if key in factors:
        out.append(est * factors[key])
        break
  return np.asarray(out)


def in_material(r: dict, densities: np.ndarray) -> np.ndarray:
  """Each density moved to the nearest slot of its box's material (the material known, as a
  texture could tell it)."""
  out = []
  for m, d in zip(r["material"], densities):
    slots = materials.material_slots(m)
    out.append(slot_to_density(slots[np.argmin(np.abs(slots - density_to_slot(max(d, 1.0))))]))
  return np.asarray(out)


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
  """The RMSE no reader can go below if boxes of parts under `threshold` of the tool's
  mass are read at their material's prior mean, and every other box exactly."""
  variance = {m: float(np.var(materials.material_slots(m))) for m in materials.MATERIALS}
  share = np.concatenate([r["share"] for r in rows])
  mats = np.concatenate([r["material"] for r in rows])
  hidden = share < threshold
  mse = sum(variance[str(m)] for m in mats[hidden]) / len(share)
  names = {}
  for r in rows:
    for s, m in zip(r["share"], r["material"]):
      if s < threshold:
        names[f"{r['category']} ({m})"] = names.get(f"{r['category']} ({m})", 0) + 1
  return {"threshold": threshold, "hidden_boxes_pct": float(100 * hidden.mean()),
          "rmse_floor": float(np.sqrt(mse)), "hidden_by_category": names}


def per_box(rows: list[dict], values) -> tuple[np.ndarray, np.ndarray]:
  """(errors in slots, tool of each box) of per-configuration density estimates."""
  err = np.concatenate([density_to_slot(np.maximum(v, 1.0)) - r["slot"]
                        for r, v in zip(rows, values)])
  tool = np.concatenate([[r["tool"]] * r["count"] for r in rows])
  return err, tool


def network_errors(rec: dict, rows: list[dict]) -> tuple[np.ndarray, list[int]]:
  """(per-box errors of the records' PPD guesses, positions of configurations whose
  records' true slots differ from the rebuilt ones)."""
  guess, slot = np.asarray(rec[("guess", "PPD")]), np.asarray(rec[("true_slot",)])
  valid = np.asarray(rec[("true_valid",)])
  bad = [i for i, r in enumerate(rows)
         if valid[i].sum() != r["count"] or not np.array_equal(slot[i, :r["count"]], r["slot"])]
  err = np.concatenate([guess[i, :r["count"]] - slot[i, :r["count"]]
                        for i, r in enumerate(rows)])
  return err, bad


def markdown(out: dict) -> str:
  fmt = lambda s, k: f"{s[k]:.1f} [{s[k + '_ci'][0]:.1f}, {s[k + '_ci'][1]:.1f}]"
  lines = ["# What the tools' densities allow (Table 3's test split)", "", "```",
           out["command"], "```", "",
           f"{out['tools']} test tools x {out['configs']} configurations, {out['boxes']} "
           f"boxes ({out['left_out']} configurations left out: records differ from the "
           f"rebuilt tool); fill factors from {out['calibrate_tools']} tools of seed "
           f"{out['calibrate_seed']}. Intervals: 95 % bootstrap over tools.", "",
           "| reader | top-1 (%) | within 2 slots (%) | within 5 (%) | RMSE (slots) |",
           "|---|--:|--:|--:|--:|"]
  for name, s in out["readers"].items():
    lines.append(f"| {name} | {fmt(s, 'top1')} | {fmt(s, 'within2')} | {fmt(s, 'within5')}"
                 f" | {fmt(s, 'rmse')} |")
  lines += ["", "| parts under this share of the tool's mass | boxes (%) | RMSE floor "
            "(slots) | which |", "|--:|--:|--:|---|"]
  for f in out["floors"]:
    which = ", ".join(f"{k} {v}" for k, v in sorted(f["hidden_by_category"].items()))
    lines.append(f"| {100 * f['threshold']:.0f} % | {f['hidden_boxes_pct']:.1f} | "
                 f"{f['rmse_floor']:.2f} | {which} |")
  return "\n".join(lines) + "\n"


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--records", required=True, help="the tools evaluation's kept records")
  p.add_argument("--out", required=True)
  p.add_argument("--tools", type=int, default=0, help="the first N test tools (0: all)")
  p.add_argument("--calibrate_seed", type=int, default=8)
  p.add_argument("--calibrate_tools", type=int, default=100)
  p.add_argument("--calibrate_configs", type=int, default=4)
  p.add_argument("--size", default="paper", help="the tools preset's size of the data")
  a = p.parse_args()
  if not os.path.exists(a.records):
    raise SystemExit(f"not found: {a.records}")
  preset = tools_preset.get_config(a.size)
  data, configs = preset.data, int(preset.data.configs_per_tool)
  ids = test_tools(data.num_tools, data.split_fractions)
  rec = partial.saved_records(a.records)
  if len(rec[("blocks",)]) != len(ids) * configs:
    raise SystemExit(f"{len(rec[('blocks',)])} records, but the preset's test split has "
                     f"{len(ids) * configs} objects: records of another dataset")
  ids = ids[:a.tools] if a.tools else ids
  rows = [r for i in tqdm(ids, desc="test tools") for r in tool_rows(preset.seed, int(i),
                                                                     configs)]
  calib = [r for i in tqdm(range(a.calibrate_tools), desc="calibration tools")
           for r in tool_rows(a.calibrate_seed, i, a.calibrate_configs)]
  net_err, bad = network_errors({k: np.asarray(v)[:len(rows)] for k, v in rec.items()}, rows)
  keep_cfg = np.ones(len(rows), bool)
  keep_cfg[bad] = False
  keep_box = np.concatenate([[k] * r["count"] for k, r in zip(keep_cfg, rows)])
  kept = [r for r, k in zip(rows, keep_cfg) if k]
  factors = fill_factors(calib)
  oracle, tool = per_box(kept, [r["oracle"] for r in kept])
  fitted, _ = per_box(kept, [calibrated(r, factors) for r in kept])
  known, _ = per_box(kept, [in_material(r, calibrated(r, factors)) for r in kept])
  share = np.concatenate([r["share"] for r in kept])
  seen = share >= HIDDEN[0]
  readers = {
      "the shipped model, PPD (full) (records)": scores(net_err[keep_box], tool),
      f"the shipped model, boxes of parts >= {HIDDEN[0]:.0%} of the mass":
          scores(net_err[keep_box][seen], tool[seen]),
      f"the shipped model, boxes of parts < {HIDDEN[0]:.0%} of the mass":
          scores(net_err[keep_box][~seen], tool[~seen]),
      "oracle mass properties, true boxes": scores(oracle, tool),
      "oracle mass properties, true boxes, fill calibrated": scores(fitted, tool),
      "the same, each box's material known": scores(known, tool)}
  command = (f"python experiments/tool_density_ceiling.py --records={a.records} "
             f"--out={a.out}" + (f" --tools={a.tools}" if a.tools else ""))
  out = {"command": command, "tools": len(ids), "configs": configs,
         "boxes": int(keep_box.sum()), "left_out": len(bad),
         "calibrate_seed": a.calibrate_seed, "calibrate_tools": a.calibrate_tools,
         "readers": readers, "floors": [floor(kept, t) for t in HIDDEN],
         "fill_factors": {"/".join(map(str, k)): v for k, v in factors.items()}}
  os.makedirs(a.out, exist_ok=True)
  with open(os.path.join(a.out, "results.json"), "w") as f:
    json.dump(out, f, indent=1)
  md = markdown(out)
  with open(os.path.join(a.out, "results.md"), "w") as f:
    f.write(md)
  print(md)


if __name__ == "__main__":
  main()
