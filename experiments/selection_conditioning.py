"""Why +Sample's closest trajectory rarely holds the right slots: what each kind of density
error costs in trajectory distance (the +Sample objective at τ = 0), on the true boxes of
towers of a fresh seed under the paper's four pushes.

Per tower, the distance (`metrics.trajectory_distance`, mm) between the true densities'
trajectories and those of:
  scale ±δ      every density × (1 ± δ): the total mass off by δ, the split between the
                blocks kept;
  split ε       mass moved between two blocks at a fixed total mass (block a's density
                × (1 + ε), block b's lowered to keep the total), for every ordered pair;
                the pair that costs least, and the median pair;
  ±k slots      every block's density off by k slots (100 kg/m³ each) with random signs,
                the errors of the best sample an oracle could pick (`evaluate`'s "+Sample's
                ceiling": RMSE about 2.5 slots).
Each row also gives the slot RMSE of the perturbation, so that the last column, distance
per slot of RMSE, says how stiff the distance is in that direction.

    python experiments/selection_conditioning.py --towers=48

Writes experiments/results/selection_conditioning.{json,md}. MuJoCo C simulates (the
reference engine; the JAX engines follow it to about a millimetre).
"""

import json
import os
import sys
import time

import jax
import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.conventions import SLOT_DENSITY
from ppdjax.dataset import towers
from ppdjax.sim.simulate import simulate

_TOWERS = flags.DEFINE_integer("towers", 48, "Towers (one configuration each).")
_SEED = flags.DEFINE_integer("seed", 20261126, "Their seed (never trained on).")
_OUT = flags.DEFINE_string("out", "experiments/results/selection_conditioning",
                           "Output path without extension.")

SCALES = (0.01, 0.03, 0.1)
SPLITS = (0.1, 0.3)
SLOT_OFFSETS = (1, 2, 3)


def variants(prims, rng):
  """(name, parameter, densities (V, K)) of one tower's perturbations (K slots, n valid)."""
  d = np.asarray(prims.density, np.float64)
  valid = np.asarray(prims.valid)
  vol = np.prod(2.0 * np.asarray(prims.half_size, np.float64), -1)
  n = int(valid.sum())
  out = []
  for s in SCALES:
    for sign in (1, -1):
      out.append(("scale", s, d * (1 + sign * s)))
  for e in SPLITS:
    for a in range(n):
      for b in range(n):
        if a == b:
          continue
        moved = d.copy()
        moved[a] *= 1 + e
        moved[b] -= vol[a] * d[a] * e / vol[b]
        if moved[b] >= 50.0:  # a density must stay positive (and not absurdly light)
          out.append(("split", e, moved))
  for k in SLOT_OFFSETS:
    for _ in range(4):
      signs = rng.choice((-1.0, 1.0), size=d.shape)
      out.append(("slots", k, np.maximum(d + k * SLOT_DENSITY * signs, SLOT_DENSITY)))
  return out


def main(argv):
  del argv
  t0 = time.time()
  rng = np.random.default_rng(_SEED.value)
  prims = towers.sample_towers(_SEED.value, _TOWERS.value)
  observed = np.asarray(simulate(prims, backend="mujoco"))  # (N, P, T, 7)
  rows = []  # (tower, kind, parameter, slot RMSE, distance mm)
  for i in range(_TOWERS.value):
    one = jax_free_index(prims, i)
    vs = variants(one, rng)
    dens = np.stack([v[2] for v in vs])
    batch = one.replace(density=np.asarray(dens, np.float32),
                        half_size=np.broadcast_to(one.half_size, dens.shape + (3,)),
                        pos=np.broadcast_to(one.pos, dens.shape + (3,)),
                        quat=np.broadcast_to(one.quat, dens.shape + (4,)),
                        valid=np.broadcast_to(one.valid, dens.shape))
    sims = np.asarray(simulate(batch, backend="mujoco"))
    dist = 1e3 * np.asarray(metrics.trajectory_distance(sims, observed[i][None]))
    valid = np.asarray(one.valid)
    for (kind, p, d), dd in zip(vs, dist):
      err = (d - np.asarray(one.density, np.float64))[valid] / SLOT_DENSITY
      rows.append((i, kind, p, float(np.sqrt(np.mean(err ** 2))), float(dd)))
    print(f"tower {i + 1}/{_TOWERS.value}", end="\r", file=sys.stderr)
  summary = []
  for kind, params in (("scale", SCALES), ("split", SPLITS), ("slots", SLOT_OFFSETS)):
    for p in params:
      sel = [r for r in rows if r[1] == kind and r[2] == p]
      per_tower = {}
      for r in sel:
        per_tower.setdefault(r[0], []).append(r)
      cheapest = [min(v, key=lambda r: r[4]) for v in per_tower.values()]
      entry = {"kind": kind, "parameter": p, "towers": len(per_tower),
               "slot_rmse_median": float(np.median([r[3] for r in sel])),
               "distance_mm_median": float(np.median([r[4] for r in sel])),
               "per_slot_mm_median": float(np.median([r[4] / max(r[3], 1e-9) for r in sel]))}
      if kind == "split":
        entry["cheapest_pair_distance_mm_median"] = float(np.median([r[4] for r in cheapest]))
        entry["cheapest_pair_slot_rmse_median"] = float(np.median([r[3] for r in cheapest]))
      summary.append(entry)
  command = "python experiments/selection_conditioning.py " + " ".join(sys.argv[1:])
  result = {"command": command, "towers": _TOWERS.value, "seed": _SEED.value,
            "engine": "mujoco", "summary": summary, "seconds": round(time.time() - t0, 1)}
  os.makedirs(os.path.dirname(_OUT.value), exist_ok=True)
  with open(_OUT.value + ".json", "w") as f:
    json.dump(result, f, indent=1)
  names = {"scale": "every density × (1 ± {p:g})", "split": "mass moved between two blocks, "
           "ε = {p:g}, total kept", "slots": "every block ±{p:g} slots, random signs"}
  lines = ["# What each density error costs in trajectory distance", "", "```", command, "```",
           "", f"{_TOWERS.value} towers of seed {_SEED.value} (true boxes, one configuration "
           "each, 2-5 blocks), the paper's four pushes, MuJoCo C; distance = +Sample's "
           "objective at τ = 0 (`metrics.trajectory_distance`), medians over towers and "
           "perturbations.", "",
           "| perturbation | slot RMSE | distance (mm) | mm per slot of RMSE | "
           "cheapest pair: slot RMSE / distance (mm) |", "|---|--:|--:|--:|--:|"]
  for e in summary:
    cheap = (f"{e['cheapest_pair_slot_rmse_median']:.1f} / "
             f"{e['cheapest_pair_distance_mm_median']:.2f}" if e["kind"] == "split" else "")
    lines.append(f"| {names[e['kind']].format(p=e['parameter'])} | {e['slot_rmse_median']:.1f} "
                 f"| {e['distance_mm_median']:.2f} | {e['per_slot_mm_median']:.2f} | {cheap} |")
  with open(_OUT.value + ".md", "w") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


def jax_free_index(prims, i):
  """Tower i of a stacked Primitives, as NumPy arrays."""
  return jax.tree.map(lambda x: np.asarray(x)[i], prims)


if __name__ == "__main__":
  app.run(main)
