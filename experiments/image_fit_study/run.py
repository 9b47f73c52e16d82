"""Face error of the image fit with and without the boxes' shadows, and from one start or
two (`image_fit.STARTS`), on fresh towers.

Towers of a seed nothing trains on, with random materials and textures, rendered by MuJoCo
through the dataset's camera and light (`dataset.render`), voxelized (`ppdjax.voxelize`)
and fitted: the voxels alone (`ppdjax.fit_boxes`), then the image fit
(`infer.image_fit.refine_batch`) from those boxes, scoring the boxes' outline alone (the
camera's light_dir None) or with their shadows under the scene's light, from one start or
from `image_fit.STARTS` (the default). Errors are fitted face - true face in mm, boxes
matched bottom to top (the voxel fit finds every box of these towers); the image fits run
side by side in one process, so their time ratios are a benchmark.

  python experiments/image_fit_study/run.py --towers=16 --rows=shadows,starts
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import numpy as np
from absl import app, flags
from tqdm import tqdm

from ppdjax.dataset import camera as camera_lib
from ppdjax.infer import image_fit
from ppdjax.metrics import FACE_NAMES, box_faces
from ppdjax.primitives import bottom_to_top

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from image_fit_study import common as image_fit_common  # noqa: E402

_TOWERS = flags.DEFINE_integer("towers", 32, "fresh towers")
_SEED = flags.DEFINE_integer("seed", 4242, "their seed (never trained on)")
_SIZE = flags.DEFINE_integer("size", 224, "image size (the paper preset renders 224)")
_CHUNK = flags.DEFINE_integer("chunk", 8, "towers fitted per call")
_OUT = flags.DEFINE_string("out", "experiments/results/image_fit_study.json", "results JSON")
_ROWS = flags.DEFINE_list("rows", ["edges", "shadows", "starts"], "image fits to run: edges "
                          "(the outline alone, one start), shadows (outline and shadows, one "
                          "start), starts (outline and shadows from image_fit.STARTS, the "
                          "default), coarse (starts, 17 offsets per face's interval instead of "
                          "33), coarse_fine5 (and 5 across each end instead of 9)")

# name: (label, with shadows, starts, sweep: offsets per face over its interval, per end)
ROWS = {"edges": ("edges", False, ((),), image_fit.SWEEP),
        "shadows": ("edges and shadows", True, ((),), image_fit.SWEEP),
        "starts": ("edges and shadows, two starts", True, image_fit.STARTS, image_fit.SWEEP),
        "coarse": ("two starts, sweep 17 x 9", True, image_fit.STARTS, (17, 9)),
        "coarse_fine5": ("two starts, sweep 17 x 5", True, image_fit.STARTS, (17, 5))}


def faces_of(prims) -> np.ndarray:
  return np.asarray(box_faces(bottom_to_top(jax.tree.map(jax.numpy.asarray, prims))))


def summary(signed_mm: np.ndarray) -> dict:
  """Median, mean and p90 of |error|, and per face its median and signed median (mm)."""
  err = np.abs(signed_mm)
  return {"faces": int(err.size), "median_mm": float(np.median(err)),
          "mean_mm": float(err.mean()), "p90_mm": float(np.percentile(err, 90)),
          "median_by_face_mm": dict(zip(FACE_NAMES, _round(np.median(err, 0)))),
          "signed_median_by_face_mm": dict(zip(FACE_NAMES, _round(np.median(signed_mm, 0))))}


def _round(values) -> list[float]:
  return [round(float(v), 2) for v in values]


def main(argv):
  del argv
  n, size = _TOWERS.value, _SIZE.value
  prims, images, voxel_fit = image_fit_common.fresh_towers(_SEED.value, n, size)
  shadows = camera_lib.camera_dict(size, size)
  unknown = sorted(set(_ROWS.value) - set(ROWS))
  if unknown:
    raise app.UsageError(f"--rows: unknown {unknown}; choose from {sorted(ROWS)}")
  cameras = {ROWS[r][0]: (shadows if ROWS[r][1] else dict(shadows, light_dir=None),
                         ROWS[r][2], ROWS[r][3]) for r in _ROWS.value}
  fits = {name: [] for name in cameras}
  seconds = {name: 0.0 for name in cameras}
  for name, (cam, starts, sweep) in cameras.items():  # compile once, off the clock
    jax.block_until_ready(image_fit.refine_batch(
        jax.tree.map(lambda a: a[:_CHUNK.value], voxel_fit), images[:_CHUNK.value], cam,
        starts=starts, sweep=sweep))
  for start in tqdm(range(0, n, _CHUNK.value), desc="image fits"):
    chunk = slice(start, start + _CHUNK.value)
    if images[chunk].shape[0] < _CHUNK.value:
      break  # whole chunks only: one compiled shape
    for name, (cam, starts, sweep) in cameras.items():
      t = time.perf_counter()
      fits[name].append(jax.block_until_ready(image_fit.refine_batch(
          jax.tree.map(lambda a: a[chunk], voxel_fit), images[chunk], cam, starts=starts,
          sweep=sweep)))
      seconds[name] += time.perf_counter() - t
  done = len(next(iter(fits.values()))) * _CHUNK.value
  valid = np.asarray(prims.valid[:done], bool)
  truth = faces_of(jax.tree.map(lambda a: a[:done], prims))
  signed = {"voxels": faces_of(jax.tree.map(lambda a: a[:done], voxel_fit))}
  for name in cameras:
    signed[name] = faces_of(jax.tree.map(lambda *a: np.concatenate(a), *fits[name]))
  out = {"towers": done, "seed": _SEED.value, "size": size,
         "rows": {name: summary(1000 * (f - truth)[valid]) for name, f in signed.items()},
         "seconds": {k: round(v, 1) for k, v in seconds.items()},
         "time_ratio_to": next(iter(seconds)),
         "time_ratios": {k: round(v / next(iter(seconds.values())), 2)
                         for k, v in seconds.items()},
         "machine": f"{jax.devices()[0].device_kind} ({jax.default_backend()}), "
                    f"{os.cpu_count()} CPU cores",
         "command": f"python experiments/image_fit_study/run.py --towers={n} --seed={_SEED.value} "
                    f"--size={size} --rows={','.join(_ROWS.value)}"
                    + (f" --out={_OUT.value}" if _OUT.value != _OUT.default else "")}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value, "w") as f:
    json.dump(out, f, indent=1)
  lines = [f"# The image fit: outline, shadows and starts on {done} fresh towers (seed "
           f"{_SEED.value}, {size}² images)", "", f"```\n{out['command']}\n```", "",
           f"Machine: {out['machine']}. Face error, fit - truth, mm (x lo ... z hi along the "
           "world axes: the camera looks from +x, -y and above, so x lo and y hi are seen "
           "only in silhouette). Every image fit keeps the floor faces and lets the other z "
           "faces move a voxel (`image_fit.face_spans`).", "",
           "| fit | median | mean | p90 | median by face | signed median by face | time |",
           "|---|--:|--:|--:|---|---|--:|"]
  for name, row in out["rows"].items():
    lines.append(f"| {name} | {row['median_mm']:.2f} | {row['mean_mm']:.2f} | "
                 f"{row['p90_mm']:.2f} | {' / '.join(map(str, row['median_by_face_mm'].values()))}"
                 f" | {' / '.join(map(str, row['signed_median_by_face_mm'].values()))} | "
                 f"{out['seconds'].get(name, '')} |")
  if len(out["time_ratios"]) > 1:
    lines += ["", f"Time against {out['time_ratio_to']} (the same towers, side by side, after "
              "compiling): " + ", ".join(f"{k} {v}×" for k, v in out["time_ratios"].items())
              + "."]
  with open(_OUT.value.replace(".json", ".md"), "w") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


if __name__ == "__main__":
  app.run(main)
