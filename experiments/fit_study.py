"""How well boxes are recovered from voxels: `read_tower` and `fit_boxes` on fresh objects.

  python experiments/fit_study.py --towers=200 --rotated=100 \
      --out=experiments/results/fit_study.json

(1) Axis-aligned towers (`ppdjax.sample_towers`): shape F1, exact box-count rate, per-face
error (mm) against the truth, exact voxel round trip, of `read_tower` and of
`fit_boxes(init=None)`. (2) Rotated objects, towers with `rotate=0.3` rad and single
boxes turned anywhere (`rotate=pi`), fitted from noisy starts (the truth with N(0, 1
voxel) on centres and half sizes, turned 10 degrees about a random axis) and without a
start: F1, mean best IoU per true box, and how often the fit ends in a local minimum,
i.e. with its exact voxelization disagreeing with the input on more than 2 % of the
filled voxels (the truth disagrees on none). Times are per object, after compilation,
on the backend at hand. Writes OUT (JSON) and OUT with .md.
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax import box_overlap, metrics, primitives
from ppdjax.dataset import towers
from ppdjax.infer import fit

_TOWERS = flags.DEFINE_integer("towers", 200, "axis-aligned towers")
_ROTATED = flags.DEFINE_integer("rotated", 100, "rotated towers (plus half as many single boxes)")
_SEED = flags.DEFINE_integer("seed", 20261123, "seed of the objects (used by no other study)")
_OUT = flags.DEFINE_string("out", "experiments/results/fit_study.json", "JSON results")

VOXEL_MM = 1000.0 / 32
NOISE_VOXELS, NOISE_DEGREES, LOCAL_MIN = 1.0, 10.0, 0.02


def timed(fn, *args):
  """(jax.jit(fn)(*args) as NumPy, ms per object), compiled first, then timed once."""
  compiled = jax.jit(fn).lower(*args).compile()
  t = time.perf_counter()
  out = jax.block_until_ready(compiled(*args))
  return jax.tree.map(np.asarray, out), 1000 * (time.perf_counter() - t) / len(args[0])


def shape_scores(pred, true, vox, chunk=16) -> dict:
  """F1, exact counts, best IoU per true box, voxel disagreement of `pred` (N objects)."""
  counts = jax.jit(metrics.shape_counts)
  iou_fn = jax.jit(lambda p, t: box_overlap.box_iou(t, p).max(-1))
  parts, ious = [], []
  for i in range(0, len(vox), chunk):
    p, t = (jax.tree.map(lambda x: jnp.asarray(x[i:i + chunk]), a) for a in (pred, true))
    parts.append(jax.tree.map(np.asarray, counts(p, t)))
    ious.append(np.asarray(iou_fn(p, t)))
  c = {k: np.concatenate([q[k] for q in parts]) for k in parts[0]}
  iou = np.concatenate(ious)[np.asarray(true.valid)]
  miss = (ppdjax.voxelize(pred) != vox).reshape(len(vox), -1).sum(-1)
  rel = miss / vox.reshape(len(vox), -1).sum(-1)
  return {"f1": metrics.f1_from_counts(**c),
          "exact_count_rate": float(np.mean(c["predicted"] == c["true"])),
          "mean_best_iou": float(iou.mean()), "true_boxes_iou_below_0.5": float(np.mean(iou < 0.5)),
          "voxel_exact_rate": float(np.mean(miss == 0)),
          "disagreement_percent_mean": float(100 * rel.mean()),
          "disagreement_percent_median": float(100 * np.median(rel)),
          "local_minimum_rate": float(np.mean(rel > LOCAL_MIN))}


def face_errors_mm(pred, true) -> dict:
  """Per-face |error| (mm) of axis-aligned boxes, both bottom to top, same-count objects."""
  same = np.asarray(pred.valid).sum(-1) == np.asarray(true.valid).sum(-1)
  v = np.asarray(true.valid) & same[:, None]
  faces = lambda p, s: np.asarray(p.pos) + s * np.asarray(p.half_size)
  err = np.concatenate([np.abs(faces(pred, s) - faces(true, s))[v] for s in (-1, 1)]).ravel()
  err *= 1000.0
  return {"mean": float(err.mean()), "median": float(np.median(err)),
          "p90": float(np.percentile(err, 90)), "max": float(err.max()), "faces": int(err.size)}


def noisy(prims, rng):
  """The boxes with N(0, 1 voxel) on centres and half sizes, turned 10 degrees about random axes."""
  n, k = prims.valid.shape
  half = np.maximum(prims.half_size + rng.normal(0, NOISE_VOXELS / 32, (n, k, 3)), 1 / 64)
  pos = prims.pos + rng.normal(0, NOISE_VOXELS / 32, (n, k, 3))
  axis = rng.normal(size=(n, k, 3))
  axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
  a = np.deg2rad(NOISE_DEGREES) / 2
  turn = np.concatenate([np.full((n, k, 1), np.cos(a)), np.sin(a) * axis], -1)
  quat = np.asarray(primitives.quat_mul(jnp.asarray(turn, jnp.float32), jnp.asarray(prims.quat)))
  v = prims.valid[..., None]
  return primitives.Primitives(np.where(v, half, 0).astype(np.float32),
                               np.where(v, pos, 0).astype(np.float32),
                               np.where(v, quat, [1, 0, 0, 0]).astype(np.float32),
                               prims.density, prims.valid)


def axis_aligned(seed: int, count: int) -> dict:
  true = jax.tree.map(np.asarray, primitives.bottom_to_top(ppdjax.sample_towers(seed, count)))
  vox = ppdjax.voxelize(true)
  out = {"objects": count}
  for name, fn in (("read_tower", fit.read_tower), ("fit_boxes", fit.fit_boxes)):
    pred, ms = timed(fn, vox)
    out[name] = {**shape_scores(pred, true, vox), "face_error_mm": face_errors_mm(pred, true),
                 "ms_per_object": ms}
    print(name, out[name], flush=True)
  return out


def rotated(rng, count: int, rotate: float, num_blocks=None) -> dict:
  true = primitives.stack([primitives.make(*towers.sample_geometry(rng, num_blocks,
                                                                   rotate=rotate))
                           for _ in range(count)])
  vox = ppdjax.voxelize(true)
  start = noisy(true, rng)
  out = {"objects": count, "rotate_rad": rotate, "blocks": num_blocks or "2-5",
         "noisy_start": shape_scores(start, true, vox)}
  runs = (("fit_from_start", fit.fit_boxes, {}),
          ("fit_from_start_jitter1_points512", fit.fit_boxes,
           {"jitter_starts": 1, "points": 512}),
          ("fit_without_start", fit.fit_boxes, None))
  for name, fn, options in runs:
    if options is None:
      pred, ms = timed(fn, vox)
    else:
      pred, ms = timed(lambda v, s, o=options: fn(v, s, **o), vox, start)
    out[name] = {**shape_scores(pred, true, vox), "ms_per_object": ms, "options": options}
    print(name, rotate, out[name], flush=True)
  return out


def markdown(r: dict) -> str:
  lines = [f"# Box fitting from voxels\n\n    {r['command']}\n",
           f"Backend: {r['device']}; objects from seed {r['seed']}. Local minimum: final voxel "
           f"disagreement > {100 * LOCAL_MIN:.0f} % of the filled voxels (the truth has 0). "
           f"Noisy start: truth + N(0, {NOISE_VOXELS:g} voxel) on centres and half sizes, "
           f"turned {NOISE_DEGREES:g} deg about a random axis. ms/object: one batched call "
           f"after compilation (load average {r.get('load_average', '?')} at the start; on a "
           "CPU shared with other jobs, an upper bound).\n",
           "## Axis-aligned towers\n",
           "| method | F1 | exact count | voxels exact | face error mm mean / median / p90 / max "
           "| ms/object |", "| --- | --- | --- | --- | --- | --- |"]
  for name in ("read_tower", "fit_boxes"):
    m = r["axis_aligned"][name]
    e = m["face_error_mm"]
    lines.append(f"| {name} | {m['f1']:.1f} | {100 * m['exact_count_rate']:.1f} % | "
                 f"{100 * m['voxel_exact_rate']:.1f} % | {e['mean']:.1f} / {e['median']:.1f} / "
                 f"{e['p90']:.1f} / {e['max']:.1f} | {m['ms_per_object']:.1f} |")
  lines += ["\n## Rotated objects\n",
            "| objects | method | F1 | mean best IoU | true boxes IoU < 0.5 | exact count | "
            "disagreement % mean / median | local minima | ms/object |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
  for key, res in r["rotated"].items():
    for name in ("noisy_start", "fit_from_start", "fit_from_start_jitter1_points512",
                 "fit_without_start"):
      m = res[name]
      ms = f"{m['ms_per_object']:.1f}" if "ms_per_object" in m else "-"
      lines.append(f"| {key} | {name} | {m['f1']:.1f} | {m['mean_best_iou']:.3f} | "
                   f"{100 * m['true_boxes_iou_below_0.5']:.1f} % | "
                   f"{100 * m['exact_count_rate']:.1f} % | "
                   f"{m['disagreement_percent_mean']:.2f} / {m['disagreement_percent_median']:.2f}"
                   f" | {100 * m['local_minimum_rate']:.1f} % | {ms} |")
  return "\n".join(lines) + "\n"


def main(_):
  seed = _SEED.value
  result = {"command": "python " + " ".join(sys.argv), "seed": seed,
            "device": jax.devices()[0].device_kind,
            "load_average": round(os.getloadavg()[0], 1),
            "axis_aligned": axis_aligned(seed, _TOWERS.value)}
  rng = np.random.default_rng(seed + 1)
  result["rotated"] = {
      f"towers rotate 0.3 (n={_ROTATED.value})": rotated(rng, _ROTATED.value, 0.3),
      f"single boxes rotate pi (n={_ROTATED.value // 2})": rotated(rng, _ROTATED.value // 2,
                                                                  np.pi, 1)}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value, "w") as f:
    json.dump(result, f, indent=1)
  with open(os.path.splitext(_OUT.value)[0] + ".md", "w") as f:
    f.write(markdown(result))
  print(markdown(result))


if __name__ == "__main__":
  app.run(main)
