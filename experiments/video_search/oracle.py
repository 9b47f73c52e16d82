"""Is it the search or the boxes? (issue 64) On the look-alike towers, the true densities
and shells put on the boxes `decompose` fitted, simulated as refinement simulates them, and
their distance to the tracked trajectory beside the refined answer's.

  python experiments/video_search/oracle.py --towers=ROOT/test_towers.npz \
      --answers=ROOT/decompositions_refine.npz --out=experiments/results/video_search.json \
      --section=oracle_test

A truth closer to the tracked motion than the answer the search and refinement returned
says the search stopped short on that tower. A truth far from the tracked motion on the
fitted boxes but close on the true ones says the fitted boxes cannot carry the true
densities, and least squares moves the densities to make up for them. The answer's
distance is the score `decompose` saved (the same engine; its boxes' inertia scales are
not saved, so it is not simulated again).
"""

from __future__ import annotations

import json
import os
import sys
import time

from absl import app, flags

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from ppdjax import metrics  # noqa: E402
from ppdjax.configs import video  # noqa: E402
from ppdjax.dataset import generation  # noqa: E402
from ppdjax.primitives import FIELDS, Primitives  # noqa: E402
from ppdjax.reproduce.video_report import matched, nearest_boxes, rmse_slots  # noqa: E402
from ppdjax.sim.rollout_mjx import jax_engine, simulate  # noqa: E402

flags.DEFINE_string("towers", None, "A video pipeline's test_towers.npz (truth, tracked).")
flags.DEFINE_string("answers", None, "Its decompositions_refine.npz (boxes, score).")
flags.DEFINE_string("out", None, "The results file (JSON; other keys kept).")
flags.DEFINE_string("section", "oracle", "This run's key in --out.")
FLAGS = flags.FLAGS
WAY = "tracked"
GOOD_FACES_MM = 0.5  # faces within this: refinement on true boxes' neighbours is near exact


def matching_checks(test: dict, ev: dict) -> dict:
  """What the oracle's matching assumes, counted: one box per block, boxes axis-aligned."""
  nearest = nearest_boxes(test, ev, WAY)
  shared = sum(len(set(n[v])) < v.sum() for n, v in zip(nearest, test["valid"]))
  quat = ev[f"{WAY}_quat"][ev[f"{WAY}_valid"]]
  turned = int((np.abs(np.abs(quat[:, 0]) - 1.0) > 1e-4).sum())
  return {"towers_with_a_shared_box": int(shared), "fitted_boxes_turned": turned}


def face_errors_mm(test: dict, ev: dict) -> np.ndarray:
  """(B, K) each true block's largest face error against the answer's box nearest it
  (axis-aligned: the towers' blocks are), mm; 0 for no block."""
  pos, nearest = np.nan_to_num(ev[f"{WAY}_pos"]), nearest_boxes(test, ev, WAY)
  take = lambda a: np.take_along_axis(a, nearest[..., None], 1)  # noqa: E731
  err = np.abs(test["pos"] - take(pos)) + np.abs(test["half_size"] - take(ev[f"{WAY}_half_size"]))
  return np.where(test["valid"], 1e3 * err.max(-1), 0.0)


def on_fitted_boxes(test: dict, ev: dict) -> Primitives:
  """The answer's boxes, each carrying the density and inertia scale of the true block
  nearest its centre."""
  pos, valid = ev[f"{WAY}_pos"], ev[f"{WAY}_valid"]
  dist = np.linalg.norm(pos[:, :, None] - test["pos"][:, None], axis=-1)  # (B, K', K)
  nearest = np.argmin(np.where(test["valid"][:, None], dist, np.inf), -1)
  take = lambda a: np.take_along_axis(a, nearest, 1)  # noqa: E731
  return Primitives(ev[f"{WAY}_half_size"], np.nan_to_num(pos), ev[f"{WAY}_quat"],
                    np.where(valid, take(test["density"]), 0.0).astype(np.float32), valid,
                    inertia_scale=np.where(valid, take(test["inertia_scale"]), 1.0))


def main(argv):
  del argv
  test, ev = dict(np.load(FLAGS.towers)), dict(np.load(FLAGS.answers))
  data = video.get_config("lookalike").data
  pushes, settings = generation.pushes_of(data), jax_engine(data.backend)
  ok = np.flatnonzero(np.isfinite(test[f"{WAY}_trajectory"]).all((1, 2))
                      & ev[f"{WAY}_valid"].any(-1))
  truth = Primitives(*(test[f] for f in FIELDS), inertia_scale=test["inertia_scale"])
  observed = test[f"{WAY}_trajectory"][ok][:, None]
  steps = observed.shape[2]
  distance = {}
  start = time.time()
  for name, prims in (("truth_on_true_boxes", truth), ("truth_on_fitted_boxes",
                                                       on_fitted_boxes(test, ev))):
    traj = simulate(jax.tree.map(lambda a: np.asarray(a)[ok], prims), pushes, steps=steps,
                    settings=settings)
    distance[name] = np.asarray(metrics.trajectory_distance(traj, observed))
  distance["answer"] = ev[f"{WAY}_score"][ok]
  blocks = test["valid"].sum(-1)[ok]
  faces = face_errors_mm(test, ev)[ok]
  answer = matched(test, ev, WAY)[0]
  rmse = lambda sel: rmse_slots(answer, test, ok[sel])  # noqa: E731
  # the tracker's pose error by step: the strike's first steps apart from the rest
  error = 1e3 * np.linalg.norm(np.asarray(metrics.pose_residual(
      test[f"{WAY}_trajectory"][ok], test["true_trajectory"][ok])), axis=-1)  # (B, T)
  good = faces.max(-1) < GOOD_FACES_MM
  mm = lambda d, sel: 1e3 * float(np.median(d[sel]))  # noqa: E731
  by_blocks = lambda f: {str(b): f(blocks == b) for b in (2, 3, 4)}  # noqa: E731
  result = {"towers": int(len(ok)), "seconds": time.time() - start,
            "command": "python " + " ".join(sys.argv),
            "median_distance_mm": {name: {"all": mm(d, slice(None)), **by_blocks(
                lambda sel, d=d: mm(d, sel))} for name, d in distance.items()},
            "truth_closer_than_answer_share": by_blocks(lambda sel: float(
                (distance["answer"] > distance["truth_on_fitted_boxes"])[sel].mean())),
            "answer_rmse_slots": by_blocks(rmse),
            "tracking_error_mm_median": {"step_0": float(np.median(error[:, 0])),
                                         "step_1": float(np.median(error[:, 1])),
                                         "steps_2_on": float(np.median(error[:, 2:]))},
            **matching_checks({k: test[k][ok] for k in ("pos", "valid")},
                              {k: v[ok] for k, v in ev.items() if k.startswith(WAY)}),
            "face_error_mm": by_blocks(lambda sel: {
                q: float(np.percentile(faces[sel][test["valid"][ok][sel]], p))
                for q, p in (("median", 50), ("p90", 90))}),
            f"faces_within_{GOOD_FACES_MM}_mm": {
                f"{which}_{b}": {"towers": int(sel.sum()), "answer_rmse_slots": rmse(sel), **{
                    name: mm(d, sel) for name, d in distance.items()}}
                for b in (3, 4) for which, sel in (("all_within", good & (blocks == b)),
                                                   ("some_beyond", ~good & (blocks == b)))}}
  previous = json.load(open(FLAGS.out)) if os.path.exists(FLAGS.out) else {}
  previous[FLAGS.section] = result
  with open(FLAGS.out, "w") as f:
    json.dump(previous, f, indent=1)
  print(json.dumps(result, indent=1))


if __name__ == "__main__":
  flags.mark_flags_as_required(["towers", "answers", "out"])
  app.run(main)
