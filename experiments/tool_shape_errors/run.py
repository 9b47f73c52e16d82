"""Where a model's boxes miss a tool's true boxes: shape F1, then per true box its closest
predicted box and what replacing one attribute of it by the truth's would give.

  python -m ppdjax.generate --config=ppdjax/configs/tools.py --config.seed=7 \
      --config.data.num_tools=200 --config.data.render_workers=2 --out=DIR
  python experiments/tool_shape_errors/run.py --model=assets/tools_model --data=DIR \
      --out=experiments/results/tools_order_study/shape_errors/NAME.json [--depth_bounds=1,2]

Every sample of --data is used (a fresh seed: none was trained on). Per true box: the
predicted box of highest IoU (`box_overlap.box_iou`), matched if IoU > 0.5; the fraction
matched by how thin the true box is (its thinnest side in voxels); then the same with the
paired box's centre, rotation, sizes or thinnest side replaced by the truth's (which error
matters); centre, side and long-axis errors. Shape F1 (`metrics.shape_counts`, one-to-one
matching) with a 95 % bootstrap interval over objects.

`--depth_bounds=B1,B2` adds the same breakdown for the network's boxes refined against the
depth image (`depth_fit.refine_batch`, every face free within B voxels of the network's),
and `--fit_depth` for the evaluation's +Fit(depth) boxes (fitted to the voxels, then to
the depth within half a voxel).
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from ppdjax import metrics
from ppdjax.conventions import OBS_KEYS, VOXEL_RESOLUTION
from ppdjax.dataset.storage import open_dataset
from ppdjax.infer import depth_fit
from ppdjax.infer.fit import fit_boxes
from ppdjax.box_overlap import box_iou
from ppdjax.primitives import Primitives, quat_to_mat
from ppdjax.training import checkpoints

FLAGS = flags.FLAGS

THIN_BINS = ((0, 1), (1, 2), (2, 4), (4, 1e9))  # thinnest side, voxels
CHUNK = 50  # objects decoded at once


def _pairwise_iou(a: Primitives, b: Primitives) -> np.ndarray:
  """(N, L) IoU of a's l-th box with b's l-th box."""
  one = lambda x, y: box_iou(jax.tree.map(lambda t: t[:, None], x),
                             jax.tree.map(lambda t: t[:, None], y), VOXEL_RESOLUTION)[:, 0, 0]
  return np.asarray(jax.vmap(one)(a, b))


def _long_axis(rot_Nx3x3: np.ndarray, half_Nx3: np.ndarray) -> np.ndarray:
  return np.take_along_axis(rot_Nx3x3, half_Nx3.argmax(-1)[..., None, None], -1)[..., 0]


def analyse(pred: Primitives, true: Primitives) -> dict:
  """The breakdown above for decoded boxes `pred` (N, K) against `true` (N, L)."""
  iou = np.asarray(box_iou(pred, true, VOXEL_RESOLUTION))  # (N, K, L)
  ok = np.asarray(pred.valid)[:, :, None] & np.asarray(true.valid)[:, None, :]
  iou = np.where(ok, iou, -1.0)
  closest, best = iou.argmax(1), iou.max(1)  # (N, L)
  sel = np.asarray(true.valid)
  take = lambda f: jnp.asarray(np.take_along_axis(np.asarray(getattr(pred, f)),
                                                  closest[..., None], 1))
  paired = true.replace(half_size=take("half_size"), pos=take("pos"), quat=take("quat"))
  half_t = np.asarray(true.half_size)
  voxel = 1.0 / VOXEL_RESOLUTION
  thin = 2 * half_t.min(-1) / voxel
  out = {"objects": int(len(sel)), "true_boxes": int(sel.sum()),
         "predicted_boxes": int(np.asarray(pred.valid).sum()),
         "count_exact": float((np.asarray(pred.valid).sum(1) == sel.sum(1)).mean() * 100),
         "matched": float((best[sel] > 0.5).mean() * 100),
         "median_iou": float(np.median(best[sel])), "by_thinnest_side": {}}
  for lo, hi in THIN_BINS:
    m = sel & (thin >= lo) & (thin < hi)
    out["by_thinnest_side"][f"{lo}-{hi if hi < 1e9 else 'inf'} voxels"] = {
        "boxes": int(m.sum()), "matched": float((best[m] > 0.5).mean() * 100) if m.any()
        else None}
  half_p = np.asarray(paired.half_size).copy()
  smallest = half_p.argmin(-1)[..., None]
  np.put_along_axis(half_p, smallest, half_t.min(-1)[..., None], -1)
  swaps = {"centre": dict(pos=true.pos), "rotation": dict(quat=true.quat),
           "sizes": dict(half_size=true.half_size),
           "thinnest side": dict(half_size=jnp.asarray(half_p)),
           "centre and rotation": dict(pos=true.pos, quat=true.quat)}
  out["matched_with_true"] = {name: float((_pairwise_iou(paired.replace(**kw), true)[sel]
                                           > 0.5).mean() * 100)
                              for name, kw in swaps.items()}
  centre = np.linalg.norm(np.asarray(paired.pos) - np.asarray(true.pos), axis=-1) / voxel
  sides = np.abs(np.sort(np.asarray(paired.half_size), -1) - np.sort(half_t, -1)) * 2 / voxel
  axis_p = _long_axis(np.asarray(quat_to_mat(paired.quat)), np.asarray(paired.half_size))
  axis_t = _long_axis(np.asarray(quat_to_mat(true.quat)), half_t)
  angle = np.degrees(np.arccos(np.clip(np.abs((axis_p * axis_t).sum(-1)), 0, 1)))
  q = lambda x: {"median": float(np.median(x)), "p90": float(np.percentile(x, 90))}
  out["errors"] = {"centre_voxels": q(centre[sel]),
                   "sides_voxels_small_to_large": [q(sides[sel][:, a]) for a in range(3)],
                   "long_axis_degrees": q(angle[sel])}
  counts = jax.tree.map(np.asarray, metrics.shape_counts(pred, true))
  f1 = lambda idx: metrics.f1_from_counts(*(counts[k][idx].sum()
                                            for k in ("matched", "predicted", "true")))
  out["f1"] = f1(np.arange(len(sel)))
  out["f1_ci95"] = list(metrics.bootstrap_interval(f1, len(sel)))
  return out


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_string("model", "assets/tools_model", "The tools model.")
  flags.DEFINE_string("data", None, "A tools dataset (every sample is used).", required=True)
  flags.DEFINE_string("depth_bounds", "", "Comma-separated voxels: the network's boxes refined "
                      "to the depth within each bound.")
  flags.DEFINE_bool("fit_depth", False, "Also the voxel fit refined to the depth (the "
                    "+Fit(depth) boxes).")
  flags.DEFINE_integer("max_objects", 0, "The first N (0: all).")
  flags.DEFINE_string("out", "", "Results JSON.")


def main(argv):
  del argv
  model, _ = checkpoints.load(FLAGS.model)
  data = open_dataset(FLAGS.data)
  bounds = [float(b) for b in FLAGS.depth_bounds.split(",") if b]
  count = min(len(data), FLAGS.max_objects or len(data))
  decode = jax.jit(lambda obs: model.decode(obs)[0])
  named = {f"network+depth({b:g} voxels)": b for b in bounds}
  variants = {"network": []} | {name: [] for name in named}
  if FLAGS.fit_depth:
    variants["fit+depth"] = []
  trues = []
  for start in range(0, count, CHUNK):
    batch = data.take(np.arange(start, min(start + CHUNK, count)))
    pred = decode({k: jnp.asarray(batch[k]) for k in OBS_KEYS})
    variants["network"].append(pred)
    for name, b in named.items():
      variants[name].append(depth_fit.refine_batch(
          pred, batch["depth"], data.camera, bound=b / VOXEL_RESOLUTION))
    if FLAGS.fit_depth:
      variants["fit+depth"].append(depth_fit.refine_batch(
          fit_boxes(jnp.asarray(batch["voxels"]), init=pred), batch["depth"], data.camera))
    trues.append(jax.tree.map(jnp.asarray, batch["primitives"]))
    print(f"{start + len(trues[-1].valid)} / {count} objects", flush=True)
  cat = lambda ps: jax.tree.map(lambda *x: jnp.concatenate(x), *ps)
  true = cat(trues)
  results = {name: analyse(cat(ps), true) for name, ps in variants.items()}
  out = {"model": FLAGS.model, "data": FLAGS.data, **results.pop("network")}
  if results:
    out["variants"] = results
  for name, r in [("network", out)] + list(results.items()):
    print(f"{name}: F1 {r['f1']:.1f} [{r['f1_ci95'][0]:.1f}, {r['f1_ci95'][1]:.1f}], "
          f"matched {r['matched']:.1f} %, by thinnest side "
          f"{ {k: v['matched'] for k, v in r['by_thinnest_side'].items()} }")
  if FLAGS.out:
    os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
    with open(FLAGS.out, "w") as f:
      json.dump(out, f, indent=1)


if __name__ == "__main__":
  define_flags()
  app.run(main)
