"""The `export` and `report` steps of ppdjax.reproduce blocks: the shipped model, the example,
tables and figures.

`export_example` exports the full model to ASSETS/blocks_model, a test tower to
ASSETS/blocks_example.npz and the picture of its decomposition to
RESULTS/blocks_decomposition.png. `write_all` writes RESULTS/blocks.json and blocks.md
(Tables 2, 4, 5 beside the paper's numbers, the targets, each step's wall time and
machine), blocks_learning_curves.png and blocks_confusion.png, and takes the export as made
(or makes it when missing).
"""

from __future__ import annotations

import json
import os

import numpy as np

from ppdjax.report.provenance import row_headlines, write_provenance
from ppdjax.reproduce import blocks_common as common
from ppdjax.reproduce import steps as pipeline_steps

from ppdjax.dataset import storage
from ppdjax.infer import example
from ppdjax.report import markdown, tables
from ppdjax.report.plots import plot_confusion, plot_variant_curves
from ppdjax.training import checkpoints

ABLATIONS = {v: common.VARIANTS[v][1]
             for v in ("no_trajectory", "no_image", "no_voxels", "rgbd")}
TABLE5_ROWS = (("Texture", "no_trajectory", "PPD"), ("Physics", "no_image", "PPD"),
               ("Texture + Physics", "full", "PPD"),
               ("Texture + Physics (+Sample)", "full", "PPD+Sample"),
               ("Texture + Physics (+Sample+Refine)", "full", "PPD+Sample+Refine"),
               ("Texture + Physics (+Fit+Sample)", "full", "PPD+Fit+Sample"),
               ("Texture + Physics (+Fit+Sample+Refine)", "full", "PPD+Fit+Sample+Refine"),
               ("Texture + Physics (+Fit(depth)+Sample)", "full", "PPD+Fit(depth)+Sample"),
               ("Texture + Physics (+Fit(depth)+Sample+Refine)", "full",
                "PPD+Fit(depth)+Sample+Refine"),
               ("Texture + Physics (+Fit(depth)+Sample+Joint)", "full",
                "PPD+Fit(depth)+Sample+Joint"),
               ("Texture + Physics (true boxes +Sample+Refine, oracle)", "full",
                "PPD+True boxes+Sample+Refine"))
# the best row's own targets beyond the paper's (shape and density together)
BEST_TOP1, BEST_RMSE, BEST_ROW_FIT = 50.0, 6.5, "PPD (full)+Fit(depth)+Sample+Refine"
PIPELINE_MINUTES = 25  # generate, train the five models, evaluate: one H100
SUFFIXES = tuple(row[len("PPD"):] for row in tables.PPD_ROWS)  # "", "+Sample", ...
KEYS = ("top1", "top5", "top10", "rmse", "mae")
BEST_ROW = "PPD (full)+Sample"


def collect(pipe) -> dict:
  """blocks.json's content from the five evaluations and ROOT/steps.jsonl."""
  res = {}
  for v in ("full",) + tuple(ABLATIONS):
    if os.path.exists(pipe.eval_path(v)) or v == "full":  # a report may come before the
      with open(pipe.eval_path(v)) as f:                   # ablations are done
        res[v] = json.load(f)
  ablations = {v: name for v, name in ABLATIONS.items() if v in res}
  val = None
  if os.path.exists(pipe.val_path()):
    with open(pipe.val_path()) as f:
      v = json.load(f)
    val = {"objects": v["objects"], "prior_sweeps": v.get("prior_sweeps"), "f1": v["f1"],
           "shape_fit": v.get("shape_fit"), "shape_fit_depth": v.get("shape_fit_depth")}
  full = res["full"]
  table2 = {b: full["table2"][b] for b in tables.BASELINES}
  table2.update({name: res[v]["table2"]["PPD"] for v, name in ablations.items()})
  for suffix in SUFFIXES:
    if "PPD" + suffix in full["table2"]:
      table2["PPD (full)" + suffix] = full["table2"]["PPD" + suffix]
  objects = {k: full["objects"] for k in table2}
  objects.update({name: res[v]["objects"] for v, name in ablations.items()})
  table2 = {k: {**{m: float(r[m]) for m in KEYS}, "ci95": r.get("ci95"), "objects": objects[k]}
            for k, r in table2.items()}
  table5 = {name: res[v]["table5"][row] for name, v, row in TABLE5_ROWS
            if v in res and row in res[v]["table5"]}
  table5_ci95 = {name: res[v].get("table5_ci95", {}).get(row) for name, v, row in TABLE5_ROWS
                 if v in res and row in res[v]["table5"]}
  log = pipeline_steps.read_log(pipe.root)
  return {
      "table2": table2, "f1": full["f1"], "shape": full.get("shape"),
      "shape_fit": full.get("shape_fit"), "shape_fit_depth": full.get("shape_fit_depth"),
      "face_error_mm": full.get("face_error_mm"), "image_fit": full.get("image_fit", False),
      "f1_ablations": {name: res[v]["f1"] for v, name in ablations.items()},
      "table4": full["table4"], "table4_evaluated": full.get("table4_evaluated"), "table5": table5, "table5_ci95": table5_ci95,
      "mae_units": full["mae_units"], "objects": full["objects"], "split": full["split"],
      **{k: full.get(k) for k in tables.INTERVAL_KEYS},
      "data_kind": "towers",  # also for evaluations from before they recorded it
      "subset": full.get("subset", "first"), "samples": full["samples"],
      "refine": full["refine"],
      "prior_weight": full.get("prior_weight", 0.0), "prior_sweep": full.get("prior_sweep"),
      "network_prior_weight": full.get("network_prior_weight", -1.0),
      "prior_sweeps": full.get("prior_sweeps"), "validation": val,
      "refine_stats": full.get("refine_stats"), **log,
      "paper": {"table2": tables.PAPER_TABLE2, "table4": tables.PAPER_TABLE4,
                "table5": tables.PAPER_TABLE5, "f1": tables.PAPER_SHAPE_F1},
  }


def whole_split(r: dict, full: dict, command: str) -> dict:
  """blocks.json's "whole_split": the full model evaluated on every test object (`full`,
  an `evaluate` results.json), beside the ablations' rows (already on the whole split)."""
  rows = {b: full["table2"][b] for b in tables.BASELINES}
  rows.update({"PPD (full)" + s: full["table2"]["PPD" + s] for s in SUFFIXES
               if "PPD" + s in full["table2"]})
  table2 = {k: {**{m: float(v[m]) for m in KEYS}, "ci95": v.get("ci95"),
                "objects": full["objects"]} for k, v in rows.items()}
  for name in ABLATIONS.values():  # evaluated on the whole split by the run
    if name in r["table2"]:
      table2[name] = r["table2"][name]
  order = [k for k in (*tables.BASELINES, *ABLATIONS.values()) if k in table2]
  table2 = {k: table2[k] for k in order + [k for k in table2 if k not in order]}
  table5 = {name: r["table5"][name] for name, v, _ in TABLE5_ROWS
            if v != "full" and name in r["table5"]}
  table5.update({name: full["table5"][row] for name, v, row in TABLE5_ROWS
                 if v == "full" and row in full["table5"]})
  table5_ci95 = {name: full.get("table5_ci95", {}).get(row) for name, v, row in TABLE5_ROWS
                 if v == "full" and row in full["table5"]}
  keep = ("f1", "shape", "shape_fit", "shape_fit_depth", "face_error_mm", "image_fit", "table4",
          "table4_evaluated",
          "oracle_pick", "prior_sweeps", "refine_stats", "objects", "split", "samples",
          "refine", "prior_weight", "selection_horizon", "seconds", "seconds_by_part",
          "mae_units", *tables.INTERVAL_KEYS)
  return {**{k: full.get(k) for k in keep}, "table2": table2, "table5": table5,
          "table5_ci95": table5_ci95, "command": command}


def targets(r: dict) -> list[tuple[str, float, str, float, bool]]:
  """(what, ours, relation, target, met) for each target: the paper's best row (Table 2's
  PPD (full)+Sample, Table 5's Texture + Physics) and shape F1, for each of our rows; on
  the whole test split where it was evaluated (`whole_split`), else on the run's objects."""
  pipeline = r
  r = r.get("whole_split") or r
  best = r["table2"][BEST_ROW]
  top1, top5, top10, rmse, mae = tables.PAPER_TABLE2["PPD (full)+Sample"]
  out = [(f"{BEST_ROW} top-{k}", best[f"top{k}"], "≥", t, best[f"top{k}"] >= t)
         for k, t in ((1, top1), (5, top5), (10, top10))]
  out.append((f"{BEST_ROW} RMSE (slots)", best["rmse"], "≤", rmse, best["rmse"] <= rmse))
  ratio = best["mae"] / r["table2"]["Frequent"]["mae"]
  goal = mae / tables.PAPER_TABLE2["Frequent"][4]
  out.append((f"{BEST_ROW} MAE / Frequent MAE", ratio, "≤", round(goal, 2), ratio <= goal))
  f1 = tables.PAPER_SHAPE_F1
  out.append(("shape F1 (%)", r["f1"], "≥", f1, r["f1"] >= f1))
  for key, fit_name in (("shape_fit", "the fit"), ("shape_fit_depth", "the depth fit")):
    fit = r.get(key)
    if fit:
      out.append((f"shape F1 with {fit_name} (%)", fit["f1"], "≥", 99.5, fit["f1"] >= 99.5))
      out.append((f"box count exact with {fit_name} (%)", fit["count_exact"], "≥", 99,
                  fit["count_exact"] >= 99))
  for row in ("PPD (full)+Fit+Sample", "PPD (full)+Fit+Sample+Refine",
              "PPD (full)+Fit(depth)+Sample", "PPD (full)+Fit(depth)+Sample+Refine"):
    fs = r["table2"].get(row)
    if not fs:
      continue
    for k, t in ((1, top1), (5, top5), (10, top10)):
      out.append((f"{row} top-{k}", fs[f"top{k}"], "≥", t, fs[f"top{k}"] >= t))
    out.append((f"{row} RMSE (slots)", fs["rmse"], "≤", rmse, fs["rmse"] <= rmse))
    ratio = fs["mae"] / r["table2"]["Frequent"]["mae"]
    out.append((f"{row} MAE / Frequent MAE", ratio, "≤", round(goal, 2), ratio <= goal))
  best_fit = r["table2"].get(BEST_ROW_FIT)
  if best_fit:
    out.append((f"{BEST_ROW_FIT} top-1 (aim)", best_fit["top1"], "≥", BEST_TOP1,
                best_fit["top1"] >= BEST_TOP1))
    out.append((f"{BEST_ROW_FIT} RMSE (aim)", best_fit["rmse"], "≤", BEST_RMSE,
                best_fit["rmse"] <= BEST_RMSE))
  for label in ("Texture + Physics (+Sample)", "Texture + Physics (+Fit+Sample)",
                "Texture + Physics (+Fit+Sample+Refine)",
                "Texture + Physics (+Fit(depth)+Sample)",
                "Texture + Physics (+Fit(depth)+Sample+Refine)"):
    tp = r["table5"].get(label, {})
    for n, t in zip("2345", tables.PAPER_TABLE5["Texture + Physics"]):
      if n in tp:
        out.append((f"Table 5 {label}, {n} blocks", tp[n], "≤", t, tp[n] <= t))
  minutes = pipeline.get("wall_seconds", pipeline["total_seconds"]) / 60
  out.append(("pipeline wall time, steps logged so far (min)", round(minutes, 1), "≤",
              PIPELINE_MINUTES, minutes <= PIPELINE_MINUTES))
  return out


def steps_note(horizon) -> str:
  """What +Sample's distance covers (`eval.selection_horizon`; 0 or None: all steps)."""
  return (f"the distance over the first {horizon} steps" if horizon
          else "the distance over all steps")


def report_md(r: dict, command: str) -> str:
  devices = sorted({s["device"] for s in r["steps"].values()})
  ws_horizon = (r.get("whole_split") or {}).get("selection_horizon") or 0
  lines = ["# Block towers at paper scale: Tables 2, 4 and 5", "", "```", command, "```", "",
           f"Machine: {', '.join(devices)}. Test split, "
           + (f"first {r['objects']} objects; " if r.get("subset", "first") == "first"
              else f"{r['objects']} objects spread over the split; ")
           + f"{r['samples']} density samples" + (", LM refinement" if r["refine"] else "")
           + f"; +Sample selects by distance − {markdown.taus(r)} · log prior, "
           + steps_note(r.get("selection_horizon"))
           + (f" (the whole-split table below: {steps_note(ws_horizon)})"
              if ws_horizon != (r.get("selection_horizon") or 0) else "")
           + ". Density "
           f"top-k in %, RMSE in slots (×100 kg/m³), trajectory MAE in {r['mae_units']}.", "",
           "What each change (encoder, geometry stream, losses, fit, depth, MAP refinement) "
           "did, measured, and what is still missing: `docs/experiments.md`.", "",
           "## Targets: the paper's best row and shape F1", ""]
  ws = r.get("whole_split")
  if ws:
    lines += [f"On the whole test split ({ws['objects']} objects, the section below); the "
              "pipeline's wall time from its steps.", ""]
  lines += ["| target | ours | goal | met |", "|---|--:|--:|:-:|"]
  lines += [f"| {w} | {o:.2f} | {rel} {t} | {'yes' if ok else '**no**'} |"
            for w, o, rel, t, ok in targets(r)]
  if ws:
    lines += whole_split_md(ws, ablations_by_objects=r.get("intervals_over") != "geometries")
  studies = any("Joint" in k or "True boxes" in k for k in r["table2"])
  lines += ["", "## Table 2: density and trajectory"
            + (f" (the pipeline's own evaluation, {r['objects']} objects"
               + (", with +Joint and the true boxes)" if studies else ")") if ws else ""), ""]
  lines += table2_lines(r["table2"], r["objects"])
  lines += ["", "Objects evaluated in parentheses; " + markdown.intervals_note(r)
            + " in brackets.", "",
            f"Shape F1 of the full model: **{r['f1']:.1f}** (paper {tables.PAPER_SHAPE_F1})"
            + markdown.shape_line(r) + "; ablations: "
            + ", ".join(f"{k} {v:.1f}" for k, v in r["f1_ablations"].items()) + ".", "",
            "## Table 4: best of N samples, trajectory MAE (mm)"
            + (f" ({r['table4_evaluated']} objects)" if r.get("table4_evaluated") else ""), ""]
  lines += markdown.table4_md(r["table4"])
  if r.get("face_error_mm"):
    lines += ["", "## Face error (mm) against the true boxes, k-th box from the bottom", ""]
    lines += markdown.face_md(r["face_error_mm"], r.get("image_fit", False))
  lines += ["", "Paper (1×/8×/64×/512×): " + markdown.paper_line(tables.PAPER_TABLE4) + ".", "",
            "## Table 5: density RMSE (slots) by number of blocks", ""]
  lines += markdown.table5_md(r["table5"])
  lines += ["", "Paper: " + markdown.paper_line(tables.PAPER_TABLE5) + ".", ""]
  if r.get("validation") and r["validation"].get("prior_sweeps"):
    lines += [f"## +Sample's τ on the validation split ({r['validation']['objects']} objects)",
              "", "Where τ is to be chosen (the test split's sweep is in the full model's "
              "`eval/results.md`):", ""]
    lines += markdown.prior_sweep_md(r["validation"]["prior_sweeps"])
    lines += ["", f"This run's +Sample rows use τ = {markdown.taus(r)}.", ""]
  if r.get("refine_stats"):
    s = r["refine_stats"]
    lines += [f"Refinement lowered the trajectory distance on {100 * s['improved_fraction']:.0f}%"
              f" of objects (median ratio {s['median_distance_ratio']:.3f}).", ""]
  lines += ["## Steps (wall time)", ""] + pipeline_steps.steps_md(r) + ["",
            "![learning curves](blocks_learning_curves.png)", "",
            "![confusion](blocks_confusion.png)", "",
            "![decomposition](blocks_decomposition.png)", ""]
  return "\n".join(lines)


def table2_lines(table2: dict, objects: int) -> list[str]:
  """Markdown lines of a Table 2: each row's objects in parentheses (`objects` where the
  row does not say), 95 % intervals in brackets, the paper's row beside."""
  lines = ["| Method | Top 1 | Top 5 | Top 10 | RMSE | MAE (mm) | paper: Top 1 / 5 / 10 / RMSE "
           "/ MAE |", "|---|--:|--:|--:|--:|--:|---|"]
  for name, row in table2.items():
    paper = tables.PAPER_TABLE2.get(name)
    lines.append(f"| {name} ({row.get('objects', objects)}) | "
                 + " | ".join(markdown.with_ci(row, k) for k in KEYS) + " | "
                 + (" / ".join(str(x) for x in paper) if paper else "–") + " |")
  return lines


def whole_split_md(ws: dict, ablations_by_objects: bool = False) -> list[str]:
  """Markdown lines: Tables 2 and 5 of the full model on the whole test split, and what
  +Sample could reach on its own candidates. `ablations_by_objects`: the ablations' rows
  (the pipeline's own evaluations) have intervals over objects, unlike the full model's."""
  lines = ["", f"## Table 2 on the whole test split ({ws['objects']} objects)", "", "```",
           ws["command"], "```", "",
           f"{ws['samples']} density samples"
           + (", LM refinement from the closest sample" if ws.get("refine") else "") + ", "
           f"+Sample at τ = {ws['prior_weight']} on {steps_note(ws.get('selection_horizon'))}"
           + f"; {ws['seconds']:.0f} s on "
           f"{ws.get('machine', 'the machine in blocks_whole_split/README.md')}. Objects in "
           f"parentheses, {markdown.intervals_note(ws)} in brackets"
           + ("; the ablations' rows come from the pipeline's own evaluations, whose "
              "intervals resample single objects" if ablations_by_objects else "") + ".", ""]
  lines += table2_lines(ws["table2"], ws["objects"])
  lines += ["", f"Shape F1 **{ws['f1']:.1f}**" + markdown.shape_line(ws) + ".", "",
            "Table 5 on the whole split (density RMSE in slots; Texture and Physics: the "
            "ablations, whole split):", ""]
  lines += markdown.table5_md(ws["table5"])
  if ws.get("oracle_pick"):
    lines += ["", "+Sample's ceiling on its own candidates (`docs/experiments.md`, \"Why "
              "+Sample stays at the network's level\"):", ""]
    lines += markdown.oracle_pick_md({"oracle_pick": ws["oracle_pick"],
                                    "table2": {k.replace("PPD (full)", "PPD"): v
                                               for k, v in ws["table2"].items()}})
  return lines


def export_example(pipe, results_dir: str, assets_dir: str, exported: bool = False) -> dict:
  """The export step (beside the ablations, once the full model is trained): the full model
  to ASSETS/blocks_model, an example test tower to ASSETS/blocks_example.npz and the
  picture of its decomposition in RESULTS; returns the example's record, also saved at
  `pipe.example_record()` for the report. With `exported`, the model and example exist
  already (a report redone away from the run's machine): only the picture is made."""
  os.makedirs(results_dir, exist_ok=True)
  model_dir = os.path.join(assets_dir, "blocks_model")
  example_path = os.path.join(assets_dir, "blocks_example.npz")
  if not exported:
    checkpoints.export(pipe.workdir("full"), model_dir)
    test = storage.open_dataset(pipe.data, "test")
    index = next((i for i in range(min(len(test), 64))
                  if int(np.asarray(test[i]["primitives"].valid).sum()) == 4), 0)
    example.save_example(test[index], example_path, camera=test.camera)
  record = example.decompose_example(
      model_dir, example_path, os.path.join(results_dir, "blocks_decomposition.png"),
      samples=pipe.config.eval.samples)
  record["path"] = "blocks_decomposition.png"
  if not exported:  # what `pipe.is_exported` checks: this model, these folders
    record["exported"] = pipe.export_stamp()
    common.write_json_atomically(pipe.example_record(), record)
  return record


def write_all(pipe, results_dir: str, assets_dir: str, command: str,
              exported: bool = False) -> dict:
  """The report step: every output file; returns blocks.json's content. The export step's
  model, example and picture are taken as made (`export_example`), or made here when
  missing or older than the full model.

  With `exported`, ASSETS/blocks_model and blocks_example.npz exist already (a report
  redone away from the run's machine: no checkpoints or dataset needed).
  """
  os.makedirs(results_dir, exist_ok=True)
  r = collect(pipe)
  path = lambda name: os.path.join(results_dir, name)
  plot_variant_curves({v: os.path.join(pipe.workdir(v), "metrics.jsonl")
                       for v in ("geometry", "full") + tuple(ABLATIONS)},
                      path("blocks_learning_curves.png"))
  with open(pipe.eval_path("full")) as f:
    plot_confusion(json.load(f)["confusion"], path("blocks_confusion.png"))
  r["example"] = (export_example(pipe, results_dir, assets_dir, exported=True) if exported
                  else pipe.exported_example() if pipe.is_exported()
                  else export_example(pipe, results_dir, assets_dir))
  with open(os.path.join(assets_dir, "blocks_model", checkpoints.EXPORT)) as f:
    r["export"] = json.load(f)
  r["command"] = command
  common.save_logs(pipe, path("blocks_runs"), ("geometry", "full") + tuple(ABLATIONS))
  with open(path("blocks.json"), "w") as f:
    json.dump(r, f, indent=1)
  write_provenance(path("blocks.json"), command=command, config=pipe.config, headlines={
      **row_headlines(r["table2"], "table2", ("PPD (full)", "PPD (full)+Sample",
                                              "PPD (full)+Fit+Sample")),
      "shape F1 (learned boxes)": "shape/f1"})
  with open(path("blocks.md"), "w") as f:
    f.write(report_md(r, command))
  print(f"wrote {path('blocks.md')}, blocks.json and PNGs; model in "
        f"{os.path.join(assets_dir, 'blocks_model')}", flush=True)
  return r
