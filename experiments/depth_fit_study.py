"""Face error of boxes fitted to voxels alone and to voxels + depth, on fresh towers.

"voxels + depth" is `ppdjax.fit_boxes(voxels, depth=, camera=)`; "LM alone" the same
without its last step, the sweep that centres each face in the positions its pixels
accept (`depth_fit.sweep_faces`).

Towers of a seed nothing trains on, voxelized by `ppdjax.voxelize`, their depth rendered by
MuJoCo through the dataset's camera (`dataset.render`, `dataset.camera`). Each true face is
"seen" if the camera sees it in the true tower's own ray cast (some pixel's nearest hit
enters the box through that face). Errors are |fitted face - true face| in mm, for boxes
matched bottom to top (the fit finds every box of these towers).

  python experiments/depth_fit_study.py --towers=200 --size=224
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
from ppdjax.dataset import camera as camera_lib
from ppdjax.dataset import render
from ppdjax.dataset import depth
from ppdjax.infer import depth_fit
from ppdjax.primitives import bottom_to_top

_TOWERS = flags.DEFINE_integer("towers", 200, "fresh towers")
_SEED = flags.DEFINE_integer("seed", 20261126, "their seed (never trained on)")
_SIZE = flags.DEFINE_integer("size", 224, "depth image size (the paper preset renders 224)")
_OUT = flags.DEFINE_string("out", "experiments/results/depth_fit.json", "results JSON")


def faces_of(prims) -> np.ndarray:
  return np.asarray(metrics.box_faces(bottom_to_top(jax.tree.map(jnp.asarray, prims))))


def seen_faces(prims, cam) -> np.ndarray:
  """(K, 6) bool, bottom to top: faces through which some pixel's nearest ray enters."""
  p = bottom_to_top(jax.tree.map(jnp.asarray, prims))
  origin, dirs = depth.rays(cam)
  world = depth.to_world(p)
  d = jnp.asarray(dirs.reshape(-1, 3))
  with jax.default_matmul_precision("highest"):
    any_hit, box, t_in, _ = depth.nearest_hits(jnp.asarray(origin), d, world)
  t = jnp.take_along_axis(t_in, box[:, None], -1)[:, 0]
  point = jnp.asarray(origin) + t[:, None] * d - world.pos[box]  # axis-aligned towers
  rel = point / jnp.maximum(world.half_size[box], 1e-9)
  axis = jnp.argmax(jnp.abs(rel), -1)
  side = jnp.take_along_axis(rel, axis[:, None], -1)[:, 0] > 0
  face = axis + 3 * side
  seen = np.zeros((p.valid.shape[0], 6), bool)
  any_hit = np.asarray(any_hit)
  np.logical_or.at(seen, (np.asarray(box)[any_hit], np.asarray(face)[any_hit]), True)
  return seen


def shape_f1(fit, prims) -> float:
  c = metrics.shape_counts(jax.tree.map(jnp.asarray, fit), jax.tree.map(jnp.asarray, prims))
  return float(metrics.f1_from_counts(*(np.asarray(c[k]) for k in ("matched", "predicted",
                                                                    "true"))))


def summary(err_mm: np.ndarray) -> dict:
  """Median (with a 95 % bootstrap interval over faces), mean, p90 and max of errors."""
  err_mm = np.ravel(err_mm)
  med = lambda i: float(np.median(err_mm[i]))
  return {"faces": int(err_mm.size), "median_mm": med(np.arange(err_mm.size)),
          "median_ci95": metrics.bootstrap_interval(med, err_mm.size),
          "mean_mm": float(err_mm.mean()), "p90_mm": float(np.percentile(err_mm, 90)),
          "max_mm": float(err_mm.max())}


def main(_):
  n, size = _TOWERS.value, _SIZE.value
  prims = ppdjax.sample_towers(_SEED.value, n)
  cam = camera_lib.camera_dict(size, size)
  voxels = ppdjax.voxelize(prims)
  one = lambda i: jax.tree.map(lambda x: x[i], prims)
  with render.ObjectRenderer(size, size) as r:
    deps = np.stack([r.render(one(i), np.zeros(5, int), np.arange(5))[1]
                     for i in tqdm(range(n), desc="render depth")])
  t0 = time.perf_counter()
  plain = jax.block_until_ready(ppdjax.fit_boxes(voxels))
  t_plain = time.perf_counter() - t0
  t0 = time.perf_counter()
  with_depth = jax.block_until_ready(ppdjax.fit_boxes(voxels, depth=deps, camera=cam))
  t_depth = time.perf_counter() - t0
  t0 = time.perf_counter()  # the same without the sweep that centres faces in their runs
  lm_only = jax.block_until_ready(depth_fit.refine_batch(plain, deps, cam, sweep=False))
  t_lm = time.perf_counter() - t0
  truth = faces_of(prims)
  valid = np.asarray(prims.valid)
  same_count = np.asarray(plain.valid).sum(-1) == valid.sum(-1)
  seen = np.stack([seen_faces(one(i), cam) for i in range(n)]) & valid[..., None]
  rows = {}
  for name, fit in (("voxels", plain), ("voxels + depth, LM alone", lm_only),
                    ("voxels + depth", with_depth)):
    err = np.abs(faces_of(fit) - truth) * 1000.0
    ok = valid & same_count[:, None]
    s_ok, h_ok = seen & ok[..., None], ~seen & valid[..., None] & ok[..., None]
    rows[name] = {"seen": summary(err[s_ok]), "hidden": summary(err[h_ok]),
                  "all": summary(err[ok]),
                  "by_face": {f: summary(err[..., j][ok])
                              for j, f in enumerate(metrics.FACE_NAMES)},
                  "shape_f1": shape_f1(fit, prims)}
  out = {"command": f"python experiments/depth_fit_study.py --towers={n} --size={size}",
         "device": f"{jax.device_count()} x {jax.devices()[0].device_kind}",
         "seed": _SEED.value, "towers": n, "image_size": size,
         "towers_with_every_box_found": int(same_count.sum()),
         "seen_fraction": float(seen.sum() / (valid.sum() * 6)),
         "seconds": {"fit": round(t_plain, 1), "fit_with_depth": round(t_depth, 1),
                     "fit_with_depth_lm_alone": round(t_lm, 1)},
         "rows": rows}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value, "w") as f:
    json.dump(out, f, indent=1)
  for name, r in rows.items():
    print(f"{name:15s} seen faces median {r['seen']['median_mm']:.2f} mm "
          f"(p90 {r['seen']['p90_mm']:.1f}), hidden {r['hidden']['median_mm']:.2f} mm, "
          f"all {r['all']['median_mm']:.2f} mm; F1 {r['shape_f1']:.1f}")
  print(f"fit {t_plain:.1f} s, with depth {t_depth:.1f} s for {n} towers -> {_OUT.value}")


if __name__ == "__main__":
  app.run(main)
