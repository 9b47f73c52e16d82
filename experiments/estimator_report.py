"""The report of `estimator_study.py`: estimator.{md,json}, its training curve, the evaluations.

Reads the study's root (the estimator's metrics.jsonl and estimator.json, the validation
and test evaluations, steps.jsonl, the data's card.md); writes into OUT (experiments/results):
estimator.md, estimator.json, estimator_training.png and estimator_evals/*.json (each
evaluation without its confusion matrices).
"""

from __future__ import annotations

import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ppdjax.infer import markdown, tables  # noqa: E402

COLS = ("top1", "top5", "top10", "rmse", "mae")


def _read(path):
  with open(path) as f:
    return json.load(f)


def _rows(results: dict, names) -> dict:
  return {n: results["table2"][n] for n in names if n in results["table2"]}


def _table(entries) -> list[str]:
  """entries: (label, row) pairs -> a Table 2-like markdown table with intervals."""
  lines = ["| boxes and densities | Top 1 | Top 5 | Top 10 | RMSE | MAE (mm) |",
           "|---|--:|--:|--:|--:|--:|"]
  for label, r in entries:
    lines.append(f"| {label} | " + " | ".join(markdown.with_ci(r, k) for k in COLS) + " |")
  return lines


def plot_training(metrics: list[dict], path: str) -> None:
  steps = [m["step"] for m in metrics]
  fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
  ax[0].plot(steps, [m["val_top1"] for m in metrics], "o-", label="top-1")
  ax[0].plot(steps, [m["val_top5"] for m in metrics], "s-", label="top-5")
  ax[0].set(xlabel="step", ylabel="%", title="validation (simulated towers)")
  ax[0].legend()
  ax[1].plot(steps, [m["val_rmse"] for m in metrics], "o-", label="validation RMSE (slots)")
  ax[1].plot(steps, [m["loss"] for m in metrics], "s-", label="training loss (nats)")
  ax[1].set(xlabel="step")
  ax[1].legend()
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def write(p: dict, weights, out: str, command: str) -> dict:
  """Writes the report from the study's paths `p` (`estimator_study.paths`)."""
  os.makedirs(os.path.join(out, "estimator_evals"), exist_ok=True)
  metrics = [json.loads(line) for line in open(os.path.join(p["est"], "metrics.jsonl"))]
  est_record = _read(os.path.join(p["est"], "estimator.json"))
  val = _read(os.path.join(p["val"], "results.json"))
  ref = _read(os.path.join(p["test_reference"], "results.json"))
  tests = {w: _read(os.path.join(p[f"test_w{w}"], "results.json")) for w in weights}
  steps = [json.loads(line) for line in open(p["steps"])]
  plot_training(metrics, os.path.join(out, "estimator_training.png"))
  for name, r in [("val", val), ("test_reference", ref)] + [(f"test_w{w}", r)
                                                            for w, r in tests.items()]:
    with open(os.path.join(out, "estimator_evals", name + ".json"), "w") as f:
      json.dump({k: v for k, v in r.items() if k != "confusion"}, f, indent=1)

  est = "PPD+Fit(depth)+Est"
  entries = [("network's boxes, network's arg-max (PPD)", ref["table2"]["PPD"]),
             ("depth-fitted boxes, +Sample (reference)", ref["table2"]["PPD+Fit(depth)+Sample"]),
             ("depth-fitted boxes, +Sample+Refine (reference)",
              ref["table2"]["PPD+Fit(depth)+Sample+Refine"]),
             ("estimator alone, arg-max", tests[weights[0]]["table2"]["Estimator"])]
  for w, r in tests.items():
    entries += [(f"network + {w} × estimator, arg-max", r["table2"][est]),
                (f"network + {w} × estimator, +Sample", r["table2"][est + "+Sample"]),
                (f"network + {w} × estimator, +Sample+Refine", r["table2"][est + "+Sample+Refine"])]
  t5 = {"reference +Sample+Refine": ref["table5"]["PPD+Fit(depth)+Sample+Refine"]}
  t5.update({f"weight {w}: +Est+Sample+Refine": r["table5"][est + "+Sample+Refine"]
             for w, r in tests.items()})
  t5["paper, Texture + Physics"] = dict(zip(("2", "3", "4", "5", "overall"),
                                            tables.PAPER_TABLE5["Texture + Physics"]))
  tau = tests[weights[0]]["prior_weight"]
  card = open(os.path.join(p["data"], "card.md")).read().splitlines()[2]
  seconds = {s["step"]: s["seconds"] for s in steps}
  device = steps[0]["device"]
  lines = [
      "# The density estimator on towers of a seed never trained on", "",
      "```", command, "```", "",
      f"One {device}. {card} Each figure carries a 95 % bootstrap interval over objects. "
      "The PPD model is the shipped one (`assets/blocks_model`); boxes are fitted to the "
      "voxels and the depth image (+Fit(depth)); 512 density candidates per row; "
      "refinement: 12 Levenberg–Marquardt steps, "
      + (f"a MAP step under each row's prior (weight {ref['refine_prior']})."
         if ref["refine_prior"] else "plain least squares (no prior)."), "",
      "## The estimator", "",
      f"`ppdjax.nn.estimator.DensityEstimator`, {est_record['parameters'] / 1e6:.2f} M "
      "parameters: the boxes (extents, centre, volume, bottom to top) and the four "
      "trajectories (1-D convolutions over time) through an MLP to 100 slot logits per box. "
      f"Trained on {est_record['config']['pool_size']:,} simulated towers (fresh geometry "
      "each, the dataset's materials and slots, no rendering) for "
      f"{est_record['config']['steps']:,} steps at batch {est_record['config']['batch_size']}, "
      f"box faces jittered by {1e3 * est_record['config']['box_noise']:.0f} mm: "
      f"{seconds.get('train', 0):.0f} s in all, of which about a minute simulates the pool. "
      f"On {est_record['config']['val_size']:,} simulated validation towers it ends at "
      f"top-1 {metrics[-1]['val_top1']:.1f} %, top-5 {metrics[-1]['val_top5']:.1f} %, RMSE "
      f"{metrics[-1]['val_rmse']:.2f} slots. Shipped in `assets/density_estimator`.", "",
      "![training](estimator_training.png)", "",
      "## Test split (never trained on)", "",
      *_table(entries), "",
      f"The +Est rows select with τ = {tau}, the τ that gave the +Est+Sample row its best "
      f"top-1 on the validation split (weight {weights[0]}); the reference rows use the "
      f"preset's τ = {ref['prior_weight']}. Only the first weight was validated; the others "
      "were tried on the test split after it, so their rows are indicative. What the rows "
      "show: docs/experiments.md.", "",
      "### Density RMSE by number of blocks (Table 5)", "",
      *markdown.table5_md(t5), "",
      f"### τ on the validation split ({val['objects']} objects, weight {weights[0]}, no "
      "refinement)", "",
      *markdown.prior_sweep_md(val["prior_sweeps"]), "",
      "### Face error of the boxes the estimator reads (mm, test split)", "",
      *markdown.face_md(ref["face_error_mm"]), "",
      "## Step times", "",
      "| step | seconds |", "|---|--:|",
      *[f"| {s['step']} | {s['seconds']:.0f}" + (f" ({s['note']})" if "note" in s else "") + " |"
        for s in steps], ""]
  with open(os.path.join(out, "estimator.md"), "w") as f:
    f.write("\n".join(lines))
  summary = {"command": command, "device": device, "objects_test": ref["objects"],
             "objects_val": val["objects"], "tau": tau, "weights": list(weights),
             "estimator": {k: est_record[k] for k in ("config", "parameters", "sha256")},
             "estimator_validation": metrics[-1],
             "rows": {label: {k: r.get(k) for k in COLS} | {"ci95": r.get("ci95", {})}
                      for label, r in entries},
             "table5": t5, "steps": steps}
  with open(os.path.join(out, "estimator.json"), "w") as f:
    json.dump(summary, f, indent=1)
  return summary
