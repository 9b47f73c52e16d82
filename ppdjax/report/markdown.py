"""An evaluation's tables laid out as Markdown beside the paper's numbers (`results_md`,
`write_results`), and the pieces reports reuse (`table2_md`, `with_ci`, `paper_line`, ...)."""

from __future__ import annotations

import json
import os

from ppdjax.report.provenance import row_headlines, write_provenance
from ppdjax import metrics
from ppdjax.report.tables import (FIT_ROWS, PAPER_SHAPE_F1, PAPER_TABLE2_ONE_MODEL,
                                 PAPER_TABLE4, PAPER_TABLE5)
from ppdjax.report.plots import plot_confusion


def taus(results: dict) -> str:
  """+Sample's τ as the results record it: one, or the fitted boxes' and the network's."""
  own = results.get("network_prior_weight", -1.0)
  if own is None or own < 0:
    return f"{results['prior_weight']}"
  return f"{results['prior_weight']} (on the network's own boxes: {own})"


def face_md(face_error_mm: dict, image_fit: bool = False) -> list[str]:
  """Markdown lines: the face-error table (mm) of the network's and the fitted boxes."""
  names = {"ppd": "network's boxes",
           "fit": "+Fit (voxels and image)" if image_fit else "+Fit (voxels)",
           "fit_depth": "+Fit(depth)",
           "joint": "+Joint (faces and densities)"}
  lines = ["| boxes | faces | median | p90 | max | median by face: "
           + " / ".join(metrics.FACE_NAMES) + " |", "|---|--:|--:|--:|--:|---|"]
  for g in [g for g in names if g in face_error_mm]:
    s = face_error_mm[g]
    if s.get("faces"):
      lines.append(f"| {names[g]} | {s['faces']} | {s['median']:.2f} | {s['p90']:.2f} "
                   f"| {s['max']:.1f} | " + " / ".join(f"{v:.2f}" for v in
                                                    s["median_by_face"].values()) + " |")
  return lines


def paper_line(table: dict) -> str:
  """'row a/b/c; row d/e/f' of a paper table, for the line under a measured one."""
  return "; ".join(f"{k} {'/'.join(str(v) for v in vals)}" for k, vals in table.items())



def _sign(on: bool) -> str:
  return "+" if on else "–"


def intervals_note(results: dict) -> str:
  """What the 95 % intervals resample: single objects (results of before 2026-11-27) or
  whole towers or tools (`tables.INTERVAL_KEYS`: their count, and the data's kind)."""
  if results.get("intervals_over") != "geometries":
    return "95 % bootstrap intervals over objects"
  kind = results.get("data_kind")
  noun = "tools" if kind == "tools" else "towers" if kind else "towers or tools"
  return (f"95 % bootstrap intervals over the {results['geometries']} {noun} (each "
          "drawn with all its density configurations, which share its shape)")


def with_ci(row: dict, key: str, digits: int = 1) -> str:
  """'12.3 [11.0, 13.5]' (a value and its 95 % interval when the row has one)."""
  ci = row.get("ci95", {}).get(key)
  if row.get(key) is None:
    return "–"
  v = f"{row[key]:.{digits}f}"
  return v if ci is None else f"{v} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def table2_md(rows: dict, observes: dict) -> list[str]:
  """Markdown lines of Table 2 (95 % intervals in brackets where measured); observes[row]
  = (texture, physics) booleans."""
  lines = ["| Method | Texture | Physics | Top 1 | Top 5 | Top 10 | RMSE | MAE (mm) |",
           "|---|:-:|:-:|--:|--:|--:|--:|--:|"]
  for name, r in rows.items():
    tex, phys = observes[name]
    lines.append(f"| {name} | {_sign(tex)} | {_sign(phys)} | "
                 + " | ".join(with_ci(r, k) for k in ("top1", "top5", "top10", "rmse", "mae"))
                 + " |")
  return lines


def table4_md(table4: dict) -> list[str]:
  ns = sorted({int(n) for r in table4.values() for n in r})
  lines = ["| trajectory MAE (mm) | " + " | ".join(f"{n}×" for n in ns) + " |",
           "|---|" + "--:|" * len(ns)]
  for name in ("Sample Phys.+Shape", "Sample Phys.", "PPD") + tuple(FIT_ROWS.values()):
    if name in table4:
      lines.append(f"| {name} | " + " | ".join(f"{table4[name].get(str(n), float('nan')):.1f}"
                                               for n in ns) + " |")
  return lines


def table5_md(table5: dict) -> list[str]:
  cols = sorted({c for r in table5.values() for c in r if c != "overall"}, key=int)
  lines = ["| density RMSE (slots) | " + " | ".join(f"{c} blocks" for c in cols)
           + " | Overall |", "|---|" + "--:|" * (len(cols) + 1)]
  for name, r in table5.items():
    lines.append(f"| {name} | " + " | ".join(f"{r.get(c, float('nan')):.1f}" for c in cols)
                 + f" | {r['overall']:.1f} |")
  return lines


def prior_sweep_md(sweeps: dict) -> list[str]:
  """Markdown lines: per τ, each +Sample row's top-1 / RMSE / MAE (mm)."""
  rows = list(sweeps)
  lines = ["| τ (m per nat) | " + " | ".join(f"{r}: top-1 / RMSE / MAE" for r in rows) + " |",
           "|--:|" + "--:|" * len(rows)]
  for tau in sweeps[rows[0]]:
    lines.append(f"| {tau} | " + " | ".join(
        "{top1:.1f} / {rmse:.2f} / {mae:.1f}".format(**sweeps[r][tau]) for r in rows) + " |")
  return lines


def posterior_sweep_md(sweeps: dict) -> list[str]:
  """Markdown lines: per +Sample row and temperature, the row read by each box's posterior
  marginal: top-1 / top-5 / top-10, RMSE, MAE and Table 5's RMSE by blocks."""
  lines = ["| row | T | top-1 / top-5 / top-10 | RMSE | MAE (mm) | Table 5: 2 / 3 / 4 / 5 blocks |",
           "|---|--:|--:|--:|--:|--:|"]
  for row, sweep in sweeps.items():
    for t, o in sweep.items():
      lines.append(f"| {row} | {t} | {o['top1']:.1f} / {o['top5']:.1f} / {o['top10']:.1f} | "
                   f"{o['rmse']:.2f} | {o['mae']:.1f} | "
                   + " / ".join(f"{v:.2f}" for v in o["table5"].values()) + " |")
  return lines


def selection_sweep_md(sweep: dict) -> list[str]:
  """Markdown lines: one +Sample row's top-1 / RMSE for each τ (rows) and horizon (columns)."""
  hs = list(sweep)
  lines = ["| τ (m per nat) | " + " | ".join(f"first {h} steps" if h != "0" else "all steps"
                                            for h in hs) + " |", "|--:|" + "--:|" * len(hs)]
  for tau in sweep[hs[0]]:
    lines.append(f"| {tau} | " + " | ".join(
        "{top1:.1f} / {rmse:.2f}".format(**sweep[h][tau]) for h in hs) + " |")
  return lines


def oracle_pick_md(results: dict) -> list[str]:
  """Markdown lines: each +Sample row beside the same candidates picked by an oracle (the
  sample with the least slot error) and how many true slots any sample holds."""
  lines = ["| row | +Sample: top-1 / top-5 / RMSE | oracle's pick: top-1 / top-5 / RMSE "
           "| true slot in some sample (%) |", "|---|--:|--:|--:|"]
  for row, o in results["oracle_pick"].items():
    r = results["table2"][row]
    lines.append(f"| {row} | {r['top1']:.1f} / {r['top5']:.1f} / {r['rmse']:.2f} | "
                 f"{with_ci(o, 'top1')} / {o['top5']:.1f} / {with_ci(o, 'rmse', 2)} | "
                 f"{o['coverage']:.1f} |")
  return lines


def screen_md(results: dict) -> list[str]:
  """Markdown lines: per +Sample row and screen, how often it keeps the exhaustive pick
  and the pick's top-1 / RMSE / MAE beside the exhaustive row's."""
  lines = ["| row | screen: steps → survivors | same pick (%) | top-1 | RMSE | MAE (mm) |",
           "|---|---|--:|--:|--:|--:|"]
  for row, screens in results["screens"].items():
    r = results["table2"][row]
    lines.append(f"| {row} | none (all 512 whole) | 100 | {r['top1']:.1f} | "
                 f"{r['rmse']:.2f} | {r['mae']:.1f} |")
    for name, o in screens.items():
      steps, keep = name.split(":")
      lo, hi = o["same_pick_ci95"]
      lines.append(f"| {row} | {steps} → {keep} | {o['same_pick']:.1f} [{lo:.1f}, {hi:.1f}] | "
                   f"{o['top1']:.1f} | {o['rmse']:.2f} | {o['mae']:.1f} |")
  return lines


def results_md(results: dict, command: str = "") -> str:
  """A results.md laid out like the paper's tables, with the paper's numbers beside."""
  m = results["model"]
  observes = {name: (False, False) if name == "Frequent" else (False, True)
              if name in ("Nearest", "Estimator") else (True, False) if name == "Oracle"
              else (m["use_image"], m["use_trajectory"]) for name in results["table2"]}
  lines = [f"# Evaluation on `{results['split']}` ({results['objects']} objects)", ""]
  if command:
    lines += ["```", command, "```", ""]
  lines += [f"{results['samples']} density samples per object"
            + (f", refinement {results['refine_steps']} LM steps" if results["refine"] else "")
            + f"; {results['seconds']:.0f} s in all" + seconds_by_part(results)
            + f". Shape F1: **{results['f1']:.1f}** "
            f"(paper, block towers: {PAPER_SHAPE_F1})" + shape_line(results) + ". "
            + intervals_note(results) + ".", "",
            "## Table 2: density and trajectory", ""]
  lines += table2_md(results["table2"], observes)
  lines += ["", "Paper (block towers): " + paper_line(PAPER_TABLE2_ONE_MODEL) + ".", ""]
  if results["table4"]:
    lines += ["## Table 4: best of N samples, trajectory MAE (mm)", ""]
    lines += table4_md(results["table4"])
    if results.get("table4_evaluated", results.get("objects", 0)) < results.get("objects", 0):
      lines += ["", f"On {results['table4_evaluated']} of the {results['objects']} objects: whole "
                "batches spread over the split (`eval.table4_objects`)."]
    lines += ["", "Paper (1×/8×/64×/512×): " + paper_line(PAPER_TABLE4) + ".", ""]
  if results.get("face_error_mm"):
    lines += ["## Face error (mm) against the true boxes, k-th box from the bottom", ""]
    lines += face_md(results["face_error_mm"], results.get("image_fit", False))
    lines += [""]
  lines += ["## Table 5: density RMSE by number of blocks", ""]
  lines += table5_md(results["table5"])
  lines += ["", "Paper (2/3/4/5 blocks, overall): " + paper_line(PAPER_TABLE5) + ".", ""]
  sweeps = results.get("prior_sweeps") or (
      {"PPD+Sample": results["prior_sweep"]} if results.get("prior_sweep") else {})
  if sweeps:
    lines += ["## +Sample selection: distance − τ · log prior", ""]
    lines += prior_sweep_md(sweeps)
    lines += ["", f"Table 2's +Sample rows use τ = {taus(results)}"
              + (f" on the first {results['selection_horizon']} steps"
                 if results.get("selection_horizon") else "") + ".", ""]
  if results.get("posterior_sweeps"):
    lines += ["## +Sample read by each box's posterior marginal: p(slots) · exp(−distance / T)",
              "", "T in metres; rel:α is α × the object's least distance.", ""]
    lines += posterior_sweep_md(results["posterior_sweeps"])
    lines += [""]
  for row, sweep in results.get("selection_sweeps", {}).items():
    lines += [f"## {row}: top-1 / RMSE by τ and by the steps the distance covers", ""]
    lines += selection_sweep_md(sweep)
    lines += [""]
  if results.get("oracle_pick"):
    lines += ["## +Sample's ceiling: the best of the same samples picked by their densities",
              ""]
    lines += oracle_pick_md(results)
    lines += [""]
  if results.get("screens"):
    lines += ["## Screened selection, replayed on the same candidates", "",
              "Each screen keeps the candidates closest over the first steps and picks the "
              "best of them by the row's objective (`SelectConfig.screen_steps`, "
              "`screen_keep`); same pick: the exhaustive winner is among the survivors.", ""]
    lines += screen_md(results)
    lines += [""]
  if "refine_stats" in results:
    r = results["refine_stats"]
    lines += ["## Refinement", "",
              "Lowered the trajectory distance of the closest sample"
              + f" on {100 * r['improved_fraction']:.0f}% of objects; median ratio refined / "
              f"sampled {r['median_distance_ratio']:.3f}; mean distance "
              f"{r['mean_distance_sample_m']:.4f} → {r['mean_distance_refined_m']:.4f} m.", ""]
  return "\n".join(lines)


def seconds_by_part(results: dict) -> str:
  """' (reading a s, baselines b s, ...)' of the batches this call computed, where known."""
  parts = results.get("seconds_by_part")
  names = {"read": "reading", "baselines": "baselines' scores",
           "device": "jitted calls with their compilation",
           "records": "records (made beside the next batch)",
           "records_waited": "waiting for the records"}
  stages = results.get("seconds_by_stage", {})
  per = stages.get("batches_after_first", 0)
  steady = (f"; first batch {stages['first_batch']:.0f} s" if stages else "")
  steady += (f", {stages['compile']:.0f} s of it compiling every stage at once"
             if stages.get("compile") else " (compilation)" if stages else "")
  t4 = stages.get("table4_batches_after_first", per)  # the batches that ran Table 4's call
  steady += (", then per batch " + ", ".join(
      f"{k} {v / max(t4 if k == 'sample_table4' else per, 1):.2f} s"
      + (f" (on its {t4} batches)" if k == "sample_table4" and t4 != per else "")
      for k, v in stages["after_first"].items()) if per else "")
  return (" (of the batches computed: " + ", ".join(f"{names.get(k, k)} {v:.0f} s"
                                                    for k, v in parts.items()) + steady + ")"
          if parts else "")


def shape_line(results: dict) -> str:
  """'; 95 % interval [a, b]; boxes fitted to the voxels (+Fit): F1 c [d, e]' (and to
  voxels and depth, +Fit(depth)) where known."""
  out = ""
  if "shape" in results:
    lo, hi = results["shape"]["f1_ci95"]
    out += f", 95 % interval [{lo:.1f}, {hi:.1f}], box count exact on " \
           f"{results['shape']['count_exact']:.1f} % of objects"
  fit = "the voxels and the image (+Fit)" if results.get("image_fit") else "the voxels (+Fit)"
  for key, what in (("shape_fit", fit),
                    ("shape_fit_depth", "voxels and depth (+Fit(depth))")):
    if results.get(key):
      s = results[key]
      out += (f"; boxes fitted to {what}: F1 **{s['f1']:.1f}** [{s['f1_ci95'][0]:.1f}, "
              f"{s['f1_ci95'][1]:.1f}], box count exact on {s['count_exact']:.1f} %")
  return out


def headline_keys(results: dict) -> dict[str, str]:
  """The headline figures of an evaluation for its provenance record (name -> key): the
  row `decompose` returns (top-1 and RMSE with their 95 % intervals), its object count
  and shape F1."""
  keys = row_headlines(results["table2"], "table2", [results["headline"]], ("top1", "rmse"))
  return {**keys, "objects": "objects", "shape F1": "f1"}


def write_results(results: dict, out_dir: str, command: str = "", *, config=None,
                  weights=None) -> tuple[str, str]:
  """Writes results.json, results.md, confusion.png (when there is a confusion matrix) and
  results.json's provenance record (the run's `config` and the model, `weights`, hashed)."""
  os.makedirs(out_dir, exist_ok=True)
  json_path, md_path = os.path.join(out_dir, "results.json"), os.path.join(out_dir, "results.md")
  with open(json_path, "w") as f:
    json.dump({**results, "command": command}, f, indent=1)
  with open(md_path, "w") as f:
    f.write(results_md(results, command))
  if results.get("confusion"):
    plot_confusion(results["confusion"], os.path.join(out_dir, "confusion.png"))
  write_provenance(json_path, command=command, config=config, weights=weights,
                   headlines=headline_keys(results) if results.get("headline") else None)
  return json_path, md_path
