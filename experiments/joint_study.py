"""+Joint against +Refine from the same start: depth-fitted boxes, densities off the truth.

Fresh towers (a seed nothing trains on) with the dataset's materials and slots; their
voxels, ray-cast depth (the dataset's camera) and trajectories (MJX, `--steps` steps).
The start is what the pipeline hands refinement: boxes fitted to the voxels and the depth
image (`fit_boxes(..., depth=, camera=)`), densities the truth's times exp(N(0, σ))
(`--density_noise`, a stand-in for the best sample). Then, with no prior:

  +Refine  densities alone on the fitted boxes (`refine.refine_densities`);
  +Joint   faces and densities together, on the motion and the depth (`joint.refine_joint`).

and, to measure what the fitted faces cost, +Refine from the same start densities on
  the true boxes (the oracle);
  the true boxes with every face moved by N(0, σ) mm (`--face_noise`, axis-aligned towers);
  the fitted boxes with each face more than 1 mm off put back on the truth.

Reports the density error (slots, relative) and the face error (mm) of each, with 95 %
bootstrap intervals over towers, to experiments/results/joint_study.{json,md}.

  python experiments/joint_study.py --towers=16 --steps=96 --size=112
"""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from tqdm import tqdm

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import SLOT_DENSITY
from ppdjax.dataset import camera as camera_lib
from ppdjax.dataset import depth as depth_lib
from ppdjax.dataset import physics_stream
from ppdjax.infer.joint import refine_joint
from ppdjax.infer.refine import refine_densities
from ppdjax.primitives import bottom_to_top

_TOWERS = flags.DEFINE_integer("towers", 16, "fresh towers")
_SEED = flags.DEFINE_integer("seed", 20261127, "their seed (never trained on)")
_STEPS = flags.DEFINE_integer("steps", 96, "trajectory steps (the dataset's: 256)")
_SIZE = flags.DEFINE_integer("size", 112, "depth image size (the paper preset's: 224)")
_ITERS = flags.DEFINE_integer("iterations", 12, "LM iterations of both")
_NOISE = flags.DEFINE_float("density_noise", 0.3, "σ of the start's log-density error")
_FACE_NOISE = flags.DEFINE_list("face_noise", ["0.5", "1", "2"],
                                "σ (mm) of the face noise on the true boxes")
_JOINT = flags.DEFINE_bool("joint", True, "run +Joint too (the slowest row)")
_OUT = flags.DEFINE_string("out", "experiments/results/joint_study", "output path stem")


def interval(values) -> list[float]:
  v = np.asarray(values, np.float64)
  return list(metrics.bootstrap_interval(lambda i: float(np.mean(v[i])), len(v)))


def with_faces(prims, lo, hi):
  """Axis-aligned boxes (the towers') with the given faces (..., K, 3) in metres."""
  return prims.replace(pos=(lo + hi) / 2, half_size=(hi - lo) / 2)


def perturbed_faces(true, sigma_mm: float, key):
  """The true boxes with every face moved by N(0, σ) along its axis."""
  e = sigma_mm * 1e-3 * jax.random.normal(key, (2,) + true.pos.shape)
  return with_faces(true, true.pos - true.half_size + e[0], true.pos + true.half_size + e[1])


def corrected_faces(fitted, true, tol_mm: float = 1.0):
  """The fitted boxes with each face more than `tol_mm` off put back on the truth."""
  faces = []
  for sign in (-1, 1):
    f, t = fitted.pos + sign * fitted.half_size, true.pos + sign * true.half_size
    faces.append(jnp.where(jnp.abs(f - t) > tol_mm * 1e-3, t, f))
  return with_faces(fitted, *faces)


def main(_):
  n, t, size = _TOWERS.value, _STEPS.value, _SIZE.value
  batch = physics_stream.physics_batch(jax.random.key(_SEED.value), n, steps=t)
  true, observed = batch["primitives"], batch["trajectories"]
  cam = camera_lib.camera_dict(size, size)
  intr = jnp.asarray(cam["intrinsics"], jnp.float32)
  pose = jnp.asarray(cam["camera_from_world"], jnp.float32)
  depth = depth_lib.render_depths(true, cam)
  fitted = ppdjax.fit_boxes(ppdjax.voxelize(true), depth=depth, camera=cam)
  noise = jnp.exp(_NOISE.value * jax.random.normal(jax.random.key(_SEED.value + 1),
                                                   true.density.shape))
  start = bottom_to_top(fitted).replace(
      density=jnp.where(true.valid, true.density * noise, 0.0))  # both bottom to top
  true_start = true.replace(density=start.density)
  starts = {"+Refine on the true boxes (oracle)": true_start}
  for i, sigma in enumerate(float(x) for x in _FACE_NOISE.value):
    starts[f"+Refine on the true boxes, faces ± N(0, {sigma:g} mm)"] = perturbed_faces(
        true_start, sigma, jax.random.key(_SEED.value + 2 + i))
  starts["+Refine on the fit, faces > 1 mm off set to the truth"] = corrected_faces(start, true)
  starts["+Refine (densities alone)"] = start
  refine = jax.jit(lambda p, o: refine_densities(p, o, steps=_ITERS.value)[0])
  joint = jax.jit(lambda p, o, d: refine_joint(p, o, depth=d, intrinsics=intr,
                                               camera_from_world=pose,
                                               steps=_ITERS.value).primitives)
  one = lambda tree, i: jax.tree.map(lambda x: x[i], tree)
  runs = {name: (lambda i, s=s: refine(one(s, i), observed[i])) for name, s in starts.items()}
  if _JOINT.value:
    runs["+Joint (faces and densities)"] = lambda i: joint(one(start, i), observed[i], depth[i])
  out = {name: [] for name in runs}
  seconds = {name: 0.0 for name in runs}
  for i in tqdm(range(n), desc="towers"):
    for name, fn in runs.items():
      t0 = time.perf_counter()
      out[name].append(jax.block_until_ready(fn(i)))
      seconds[name] += time.perf_counter() - t0
  valid = np.asarray(true.valid)

  def errors(prims) -> dict:
    slot_err = (np.asarray(prims.density) - np.asarray(true.density)) / SLOT_DENSITY
    rel = np.abs(np.asarray(prims.density) / np.maximum(np.asarray(true.density), 1) - 1)
    faces = 1e3 * np.asarray(metrics.face_errors(prims, true))  # (n, K, 6) mm
    per_tower_sq = np.where(valid, slot_err ** 2, 0).sum(-1) / valid.sum(-1)
    return {"density_rmse_slots": float(np.sqrt(np.mean(slot_err[valid] ** 2))),
            "density_rmse_ci95": [float(np.sqrt(x)) for x in interval(per_tower_sq)],
            "density_rel_error_median": float(np.median(rel[valid])),
            "within_5pct": float(np.mean(rel[valid] < 0.05)),
            "face_error_median_mm": float(np.nanmedian(faces[valid])),
            "face_error_p90_mm": float(np.nanpercentile(faces[valid], 90)),
            "face_error_max_mm": float(np.nanmax(faces[valid]))}

  stack = lambda items: jax.tree.map(lambda *x: jnp.stack(x), *items)
  rows = {"start (depth fit, densities off)": errors(start)}
  rows.update({name: errors(stack(v)) for name, v in out.items()})
  command = (f"python experiments/joint_study.py --towers={n} --steps={t} --size={size} "
             f"--iterations={_ITERS.value} --density_noise={_NOISE.value} "
             f"--face_noise={','.join(_FACE_NOISE.value)}" + ("" if _JOINT.value else " --nojoint"))
  result = {"command": command, "device": f"{jax.device_count()} x {jax.devices()[0].device_kind}",
            "seed": _SEED.value, "towers": n, "boxes": int(valid.sum()),
            "seconds": {k: round(v, 1) for k, v in seconds.items()}, "rows": rows}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value + ".json", "w") as f:
    json.dump(result, f, indent=1)
  lines = ["# +Joint against +Refine from the same depth-fitted start, and what the faces cost",
           "", "```", command,
           "```", "",
           f"{result['device']}, {n} towers of seed {_SEED.value} ({result['boxes']} boxes; "
           f"2-5 blocks, the dataset's materials), trajectories of {t} steps, depth "
           f"{size}²; no prior. Every row starts from the same densities. 95 % bootstrap "
           "intervals over towers. Time for all towers, with compilation: "
           + ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items()) + ".", "",
           "| | density RMSE (slots) | median relative density error | boxes within 5 % "
           "| face error median / p90 / max (mm) |", "|---|--:|--:|--:|--:|"]
  for name, r in rows.items():
    ci = r["density_rmse_ci95"]
    lines.append(f"| {name} | {r['density_rmse_slots']:.2f} [{ci[0]:.2f}, {ci[1]:.2f}] | "
                 f"{100 * r['density_rel_error_median']:.1f} % | {100 * r['within_5pct']:.0f} % | "
                 f"{r['face_error_median_mm']:.2f} / {r['face_error_p90_mm']:.2f} / "
                 f"{r['face_error_max_mm']:.1f} |")
  with open(_OUT.value + ".md", "w") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


if __name__ == "__main__":
  app.run(main)
