"""Tracking of the video towers' test clips under one sticker layout, against the shipped
layout's figures (experiments/results/video_towers.json): clips tracked, error by clip and
by block count (.json and .md).

  python -m ppdjax.reproduce video --step=observe --root=out/video_top \
      --config.test.stickers=sides_top --workers=2
  python experiments/video_stickers/report.py --observed=out/video_top/test_towers.npz \
      --layout=sides_top --out=experiments/results/video_stickers
"""

import json
import os

import numpy as np
from absl import app, flags

from ppdjax.reproduce.video_report import tracking_errors
from ppdjax.report.provenance import write_provenance

flags.DEFINE_string("observed", "", "test_towers.npz written by the pipeline's observe step.")
flags.DEFINE_string("layout", "sides_top", "The sticker layout it was filmed with, where the "
                    "file does not say (observations made before it kept it).")
flags.DEFINE_string("baseline", "experiments/results/video_towers.json",
                    "The shipped layout's results (its 'tracking').")
flags.DEFINE_string("out", "experiments/results/video_stickers", "Path stem of .json and .md.")
FLAGS = flags.FLAGS


def per_clip(test) -> tuple[np.ndarray, np.ndarray]:
  """(clips,) median position error (mm) of each clip, NaN where it was not tracked; and
  each clip's block count."""
  tr, tt = test["tracked_trajectory"], test["true_trajectory"]
  err = np.median(1e3 * np.linalg.norm(tr[..., :3] - tt[..., :3], axis=-1), 1)
  return err, np.asarray(test["valid"]).sum(-1)


def main(argv):
  del argv
  test = dict(np.load(FLAGS.observed))
  layout = str(test.get("stickers", FLAGS.layout))
  summary = tracking_errors(test)
  err, blocks = per_clip(test)
  with open(FLAGS.baseline) as f:
    base = json.load(f)["tracking"]
  median = lambda e: (float(np.median(e[np.isfinite(e)]))  # noqa: E731
                      if np.isfinite(e).any() else None)
  result = {"layout": layout, **summary,
            "by_blocks": {str(b): {"clips": int((blocks == b).sum()),
                                   "tracked": int(np.isfinite(err[blocks == b]).sum()),
                                   "position_mm_median": median(err[blocks == b])}
                          for b in np.unique(blocks)},
            "clip_median_mm": [None if not np.isfinite(e) else float(e) for e in err],
            "baseline": {"layout": "sides", **{k: base[k] for k in (
                "clips", "tracked", "position_mm_median", "position_mm_p90_of_clip_medians",
                "rotation_deg_median")}}}
  os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
  with open(FLAGS.out + ".json", "w") as f:
    json.dump(result, f, indent=1)
  b = result["baseline"]
  command = f"python experiments/video_stickers/report.py --observed={FLAGS.observed}"
  lines = [f"# Video towers' test clips: stickers `{layout}` against `sides`", "",
           f"`{command}`", "",
           "| layout | clips tracked | median of clip medians (mm) | 90th percentile (mm) | "
           "rotation (deg) |", "|---|--:|--:|--:|--:|",
           f"| sides (shipped) | {b['tracked']} / {b['clips']} | "
           f"{b['position_mm_median']:.2f} | {b['position_mm_p90_of_clip_medians']:.2f} | "
           f"{b['rotation_deg_median']:.2f} |",
           f"| {layout} | {result['tracked']} / {result['clips']} | "
           f"{result['position_mm_median']:.2f} | "
           f"{result['position_mm_p90_of_clip_medians']:.2f} | "
           f"{result['rotation_deg_median']:.2f} |", "",
           "By block count: " + "; ".join(
               f"{k} blocks {v['tracked']} / {v['clips']} tracked, "
               f"{v['position_mm_median'] or float('nan'):.2f} mm"
               for k, v in result["by_blocks"].items()) + ".", "",
           "Failures: " + ("; ".join(result["failures"]) or "none") + "."]
  with open(FLAGS.out + ".md", "w") as f:
    f.write("\n".join(lines) + "\n")
  write_provenance(FLAGS.out + ".json", command=command)
  print("\n".join(lines))


if __name__ == "__main__":
  app.run(main)
