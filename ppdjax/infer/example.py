"""Example towers as .npz (observation and truth), decomposed with a report beside the truth."""

from __future__ import annotations

import os
import time

import jax
import numpy as np

from ppdjax import box_overlap, metrics, primitives
from ppdjax.conventions import OBS_KEYS, density_to_slot
from ppdjax.dataset.camera import check_camera
from ppdjax.dataset.readers import read_npz
from ppdjax.dataset.storage import DatasetError, MissingFileError
from ppdjax.infer.config import DecomposeConfig
from ppdjax.infer.decompose import make_decompose_fn, model_camera, model_settings
from ppdjax.report.plots import plot_decomposition
from ppdjax.primitives import Primitives
from ppdjax.training import checkpoints


def save_example(sample: dict, path: str, camera: dict | None = None) -> None:
  """Writes one dataset sample (observation and true boxes) as an .npz; with the
  dataset's `camera`, also its depth image and that camera (for the depth fit), with its
  light where the camera names one (the image fit's shadows; None: none)."""
  p = sample["primitives"]
  extra = {}
  if camera is not None:
    extra = {"depth": sample["depth"], "camera_size": [camera["height"], camera["width"]],
             "camera_intrinsics": camera["intrinsics"],
             "camera_from_world": camera["camera_from_world"]}
    if "light_dir" in camera:  # an empty array: the camera has no light
      light = camera["light_dir"]
      extra["camera_light_dir"] = np.zeros(0) if light is None else np.asarray(light)
  np.savez_compressed(path, **{k: sample[k] for k in OBS_KEYS}, **extra,
                      **{f"true_{f}": np.asarray(getattr(p, f)) for f in primitives.FIELDS})


def load_example(path: str) -> tuple[dict, Primitives]:
  """(observation, true Primitives) from an .npz written by `save_example`: "voxels"
  (32, 32, 32) of 0/1, "image" (H, W, 3) uint8, "trajectories" (P, T, 7) finite, and
  "depth" (H, W) in metres where the example has one (`load_camera` gives its camera);
  the truth's boxes as `Primitives.validate` wants them.

  Raises:
    DatasetError naming the file and what is wrong with it (MissingFileError, also a
    FileNotFoundError, for no such file).
  """
  z = read_npz(path, "example tower", error=DatasetError, missing=MissingFileError)
  bad = lambda why: DatasetError(f"{path} is not a readable example tower: {why}")
  lacks = [k for k in OBS_KEYS + tuple(f"true_{f}" for f in primitives.FIELDS)
           if k not in z]
  if lacks:
    raise bad(f"missing arrays {', '.join(lacks)} (written by save_example)")
  obs = {k: z[k] for k in OBS_KEYS + (("depth",) if "depth" in z else ())}
  shapes = {"voxels": obs["voxels"].shape == (32, 32, 32),
            "image": obs["image"].ndim == 3 and obs["image"].shape[-1] == 3,
            "trajectories": obs["trajectories"].ndim == 3 and obs["trajectories"].shape[-1] == 7,
            "depth": "depth" not in obs or obs["depth"].shape == obs["image"].shape[:2]}
  wrong = [k for k, ok in shapes.items() if not ok]
  if wrong:
    k = wrong[0]
    raise bad(f"{k} has shape {obs[k].shape}; expected voxels (32, 32, 32), image "
              "(H, W, 3), trajectories (P, T, 7), depth (H, W)")
  if obs["image"].dtype != np.uint8 or not np.isin(obs["voxels"], (0, 1)).all():
    raise bad("expected a uint8 image and voxels of 0 or 1")
  if not all(np.all(np.isfinite(obs[k])) for k in ("trajectories", "depth") if k in obs):
    raise bad("trajectories or depth contain NaN or inf")
  true = Primitives(*[z[f"true_{f}"] for f in primitives.FIELDS])
  try:
    true.validate()
  except ValueError as e:
    raise bad(f"its true boxes: {e}") from e
  return obs, true


def load_camera(path: str) -> dict | None:
  """The camera of an example's depth image (None for an example saved without one), with
  its "light_dir" where it was saved (else `camera.check_camera` gives the datasets').
  Raises DatasetError naming the file for a broken camera (`camera.check_camera`)."""
  z = read_npz(path, "example tower", error=DatasetError, missing=MissingFileError)
  if "camera_size" not in z:
    return None
  try:
    (h, w), k, pose = z["camera_size"], z["camera_intrinsics"], z["camera_from_world"]
    cam = {"height": int(h), "width": int(w), "intrinsics": k, "camera_from_world": pose}
    if "camera_light_dir" in z:
      light = z["camera_light_dir"]
      cam["light_dir"] = None if light.size == 0 else light
    check_camera(cam, z["depth"].shape if "depth" in z else None)
  except (KeyError, TypeError, ValueError) as e:
    raise DatasetError(f"{path} is not a readable example tower: its camera: "
                       f"{type(e).__name__}: {e}") from e
  return cam


def decompose_example(model_dir: str, example: str, out: str, samples: int | None = None,
                      config: DecomposeConfig | None = None, seed: int = 0) -> dict:
  """Decomposes an example tower with a trained model; saves the picture at `out`.

  Args:
    model_dir: an exported model (assets/blocks_model) or a training workdir.
    example: an .npz written by `save_example` (its camera, where it saved one, is the
      image fit's and the depth fit's).
    out: the PNG to write: the input image, the recovered boxes coloured by density and
      the truth.
    samples: density candidates, an int >= 1 (None: the config's).
    config: the decomposition settings (None: the model's own, `make_decompose_fn`'s
      default).
    seed: sampling seed.

  Raises:
    ValueError for `samples`; DatasetError (CheckpointError) naming a missing or broken
    example (model) file.

  Returns:
    {"densities": recovered kg/m³ of the valid boxes (bottom to top), "true_densities",
     "boxes", "true_boxes", "shape_matched" (boxes with IoU > 0.5), "iou" of the k-th
     recovered with the k-th true box, "distance_m", "mae_mm", "samples", "seconds" of the
     call (its compilation included), "path", "engine" (the one that simulated the
     candidates: on a CPU MuJoCo C, else the JAX engine of the model's training data)}.
  """
  if samples is not None and (isinstance(samples, bool) or not isinstance(samples, int)
                              or samples < 1):
    raise ValueError(f"samples must be a whole number >= 1 or None, got {samples!r}")
  obs, true = load_example(example)  # the cheap file first: a bad one is named at once
  trained = checkpoints.load(model_dir)
  config = model_settings(trained) if config is None else config
  if samples is not None:
    config = config.replace(**{"select.samples": samples})
  samples = config.select.samples
  # the example's own camera where it saved one, else the model's training data's
  camera = (load_camera(example) or model_camera(model_dir)) if config.fit.with_ else None
  decompose = make_decompose_fn(trained, config, camera=camera)
  key = jax.random.key(seed)
  # one call, its compilation included: a second, warm one would double the demo's wait
  # (warm latency is the benchmarks' job, experiments/benchmarks/bench_decompose.py)
  t0 = time.perf_counter()
  got = jax.block_until_ready(decompose(obs, key))
  seconds = time.perf_counter() - t0
  prims = primitives.bottom_to_top(jax.device_get(got.primitives))
  true_bt = primitives.bottom_to_top(jax.tree.map(np.asarray, true))
  valid, true_valid = np.asarray(prims.valid), np.asarray(true_bt.valid)
  dens = np.asarray(prims.density)[valid]
  true_dens = np.asarray(true_bt.density)[true_valid]
  iou = np.asarray(box_overlap.box_iou(prims, true_bt))
  plot_decomposition(obs["image"], prims, out, true=true,
                     title=f"{samples} density samples; trajectory distance "
                           f"{float(got.score) * 1e3:.0f} mm; recovered {dens.round()} kg/m³, "
                           f"true {true_dens.round()} kg/m³")
  box = lambda p, v: [{"half_size": np.asarray(p.half_size)[k].round(3).tolist(),
                       "pos": np.asarray(p.pos)[k].round(3).tolist()} for k in np.flatnonzero(v)]
  return {"densities": dens.tolist(), "true_densities": true_dens.tolist(),
          "boxes": box(prims, valid), "true_boxes": box(true_bt, true_valid),
          "shape_matched": int(metrics.match_boxes(prims, true_bt)),
          "iou": [float(iou[k, k]) for k in range(min(valid.sum(), true_valid.sum()))],
          "distance_m": float(got.score),
          "mae_mm": float(metrics.trajectory_mae(got.trajectories, obs["trajectories"])),
          "samples": samples, "fit": config.fit.enabled, "fit_with": list(config.fit.with_),
          "seconds": seconds,
          "path": out,
          "engine": engine_name(decompose.settings)}


def heaviest_line(r: dict, count: int = 2) -> str:
  """'Heaviest 2 boxes: recovered 2 and 4, true 2 and 4.' (bottom-to-top numbers)."""
  count = min(count, len(r["densities"]), len(r["true_densities"]))
  top = lambda d: " and ".join(str(k + 1) for k in sorted(np.argsort(d)[::-1][:count]))
  return (f"Heaviest {count} boxes (numbered from the bottom): recovered "
          f"{top(r['densities'])}, true {top(r['true_densities'])}.")


ENGINES = {"mjx": "MJX", "box_plane": "the box-plane step", "mujoco": "MuJoCo C"}


def boxes_line(r: dict) -> str:
  """'fitted to the voxels and the image' (or 'the network's own')."""
  if not r.get("fit", True):
    return "the network's own"
  return "fitted to " + " and ".join(["the voxels"] + ["the " + x for x in r.get("fit_with", [])])


def engine_name(settings) -> str:
  """The key in ENGINES of a simulator's settings (`decompose.settings`)."""
  from ppdjax.sim.box_plane import BoxPlaneSettings  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.rollout_mujoco import MujocoSettings  # pylint: disable=import-outside-toplevel
  return ("mujoco" if isinstance(settings, MujocoSettings) else
          "box_plane" if isinstance(settings, BoxPlaneSettings) else "mjx")


def report_md(r: dict, model_dir: str, example: str) -> str:
  """A short report: each box's recovered density and geometry beside the truth."""
  lines = [f"# `{os.path.basename(os.path.normpath(model_dir))}` on "
           f"`{os.path.basename(example)}`", "",
           f"{len(r['densities'])} boxes recovered ({boxes_line(r)}), "
           f"{len(r['true_densities'])} true; "
           f"{r['shape_matched']} match a true box at IoU > 0.5. {r['samples']} density "
           f"samples simulated with {ENGINES.get(r.get('engine', 'mjx'), r.get('engine'))}; "
           f"the closest trajectories are "
           f"{r['distance_m'] * 1e3:.1f} mm away on average (MAE {r['mae_mm']:.1f} mm). "
           f"The call, compilation included: {r['seconds']:.0f} s. {heaviest_line(r)}", "",
           "| box (bottom to top) | density (kg/m³) | true | slot error | IoU with true box |",
           "|--:|--:|--:|--:|--:|"]
  n = max(len(r["densities"]), len(r["true_densities"]))
  for k in range(n):
    got = r["densities"][k] if k < len(r["densities"]) else None
    want = r["true_densities"][k] if k < len(r["true_densities"]) else None
    err = (int(density_to_slot(got) - density_to_slot(want))
           if got is not None and want is not None else "-")
    iou = f"{r['iou'][k]:.2f}" if k < len(r["iou"]) else "-"
    fmt = lambda d: "-" if d is None else f"{d:.0f}"
    lines.append(f"| {k + 1} | {fmt(got)} | {fmt(want)} | {err} | {iou} |")
  lines += ["", f"![decomposition]({os.path.basename(r['path'])})", ""]
  return "\n".join(lines)
