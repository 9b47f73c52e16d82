"""The tools experiment's report (ppdjax.reproduce tools's last step): Table 3 beside the
paper's, shape F1, a figure of decomposed test tools, the model exported to assets/."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
from PIL import Image

from ppdjax.report.provenance import _git_state, row_headlines, write_provenance
from ppdjax.reproduce import steps as pipeline_steps

from ppdjax import make_decompose_fn
from ppdjax.infer.config import DecomposeConfig
from ppdjax.report import plots
from ppdjax.conventions import slot_to_density
from ppdjax.configs import tools as tools_preset
from ppdjax.dataset import storage, tool_generation
from ppdjax.report import tables
from ppdjax.report.markdown import intervals_note, oracle_pick_md, prior_sweep_md, table2_md
from ppdjax.training import checkpoints

FIGURE_TOOLS = 4
PRESET_TAU = tools_preset.get_config().eval.prior_weight  # +Sample's τ for tools
# Table 3 of the paper: top-1 / top-5 / top-10 (%), RMSE (slots), trajectory MAE
PAPER = {"Frequent": (2.5, 10.2, 13.6, 25.9, 348.2), "Nearest": (2.9, 8.3, 12.4, 25.8, 329.7),
         "Oracle": (7.4, 35.2, 72.0, 19.1, 185.8),
         "PPD (no trajectory)": (7.7, 36.4, 71.1, 16.8, 206.8),
         "PPD (no image)": (15.0, 56.3, 80.2, 5.9, 143.6),
         "PPD (full)": (35.7, 85.2, 95.8, 2.6, 103.6),
         "PPD (full)+Sample": (38.3, 85.0, 96.1, 2.5, 74.4)}
PAPER_F1 = 85.9


def collect(pipe) -> dict:
  """Table 3's rows (the paper's names) from the variants' evaluations, and shape F1."""
  load = lambda v: json.load(open(os.path.join(pipe.eval_dir(v), "results.json")))  # noqa: E731
  full = load("full")
  rows = {name: full["table2"][name] for name in ("Frequent", "Nearest", "Oracle")}
  rows["PPD (no trajectory)"] = load("no_trajectory")["table2"]["PPD"]
  rows["PPD (no image)"] = load("no_image")["table2"]["PPD"]
  rows["PPD (full)"] = full["table2"]["PPD"]
  rows["PPD (full)+Sample"] = full["table2"]["PPD+Sample"]
  # +Fit rows, and the oracle shape column (the true boxes: what right boxes would give)
  for extra in ("PPD+Fit", "PPD+Fit+Sample", "PPD+True boxes", "PPD+True boxes+Sample"):
    if extra in full["table2"]:
      rows[extra.replace("PPD", "PPD (full)")] = full["table2"][extra]
  return {"rows": rows, "shape": full["shape"], "shape_fit": full.get("shape_fit"),
          "objects": full["objects"], "frequent_slot": full.get("frequent_slot"),
          **{k: full.get(k) for k in tables.INTERVAL_KEYS},
          "data_kind": "tools",  # also for evaluations from before they recorded it
          "configs_per_tool": tool_generation.configs_per_tool(pipe.config.data),
          "push_force": tool_generation.push_force(pipe.config.data),
          "samples": full["samples"], "mae_units": full.get("mae_units", "mm"),
          **pipeline_steps.read_log(pipe.root)}


def figure(pipe, path: str, model_dir: str) -> str:
  """The first FIGURE_TOOLS test tools decomposed by the full model, stacked in one PNG."""
  test = storage.open_dataset(pipe.data, "test")
  # the network's boxes, as `python -m ppdjax.decompose --mesh` (the fit is worse on tools)
  decompose = make_decompose_fn(model_dir, DecomposeConfig.from_eval(pipe.config.eval).replace(
      **{"fit.enabled": False, "fit.image": False, "fit.depth": False}), pushes=test.pushes)
  panels = []
  every = tool_generation.configs_per_tool(pipe.config.data)  # one configuration a tool
  for i in range(0, min(FIGURE_TOOLS * every, len(test)), every):
    s = test[i]
    obs = {k: s[k] for k in ("voxels", "image", "trajectories")}
    d = jax.tree.map(np.asarray, decompose(obs, jax.random.key(i)))
    tmp = f"{path}.{i}.png"
    plots.plot_decomposition(s["image"], d.primitives, tmp, true=s["primitives"],
                             title=f"test tool {s['tower_id']}: trajectory distance "
                                   f"{float(d.score) * 1e3:.1f} mm")
    panels.append(np.asarray(Image.open(tmp).convert("RGB")))
    os.remove(tmp)
  Image.fromarray(np.concatenate(panels, 0)).save(path)
  return path


def _with_interval(shape: dict, key: str) -> str:
  """'50.1 [45.9, 54.5]' of a shape summary's key and its "KEY_ci95"."""
  lo, hi = shape.get(key + "_ci95") or (None, None)
  return f"{shape[key]:.1f}" + (f" [{lo:.1f}, {hi:.1f}]" if lo is not None else "")


def markdown(r: dict, command: str, stem: str = "tools") -> str:
  observes = {"Frequent": (False, False), "Nearest": (False, True), "Oracle": (True, False),
              "PPD (no trajectory)": (True, False), "PPD (no image)": (False, True)}
  rows = r["rows"]
  frequent = rows["Frequent"]["mae"]
  paper_protocol = r.get("protocol") == "paper"
  lines = ["# Tools (paper Table 3)" + (", the paper's protocol" if paper_protocol else ""),
           "", f"`{command}`", ""]
  if paper_protocol:
    lines += ["The paper's protocol (`ppdjax/configs/tools_paper.py`, docs/data.md): the tool "
              "meshes give the voxels and the image; the mesh's boxes are the body, each of "
              "a material drawn uniformly from Table 1's five, the image textured by box.", ""]
  lines += [f"{r['objects']} test objects of the procedural tools dataset (none trained on"
           + (f"; {r['objects'] // r['configs_per_tool']} tools x {r['configs_per_tool']} "
              "density configurations" if r.get("configs_per_tool", 1) > 1 else "") + "), "
           + (f"pushes of {r['push_force']:g} N, " if r.get("push_force") else "")
           + f"{r['samples']} density samples for +Sample; "
           + intervals_note(r) + f" in brackets; trajectory MAE in {r['mae_units']}.",
           ""]
  if r.get("rerun"):
    lines += [f"The full model's rows (the baselines, PPD (full) and every +Fit, +Sample and "
              f"true-box row) come from a later evaluation of the shipped model on the same "
              f"test tools, on {r['rerun']['machine']}, with +Sample at τ = "
              f"{r['rerun']['prior_weight']} (`experiments/tools_rerun/run.py`; "
              f"`tools_rerun/results.md`):", "", "```", r["rerun"]["command"], "```", "",
              "The ablations' rows come from the run above.", ""]
  lines += table2_md(rows, {k: observes.get(k, (True, True)) for k in rows})
  lines += ["", "| Method | MAE / Frequent's (ours) | paper |", "|---|--:|--:|"]
  for name, row in rows.items():
    paper = PAPER.get(name)
    lines.append(f"| {name} | {row['mae'] / frequent:.2f} | "
                 + (f"{paper[4] / PAPER['Frequent'][4]:.2f}" if paper else "–") + " |")
  slot = r.get("frequent_slot")
  lines += ["", "Frequent simulates every box at the training split's most frequent slot"
            + (f" (here slot {slot}, {float(slot_to_density(slot)):.0f} kg/m³)"
               if slot is not None else "")
            + (". With every material equally likely, stone's ten slots, which metal's lower "
               "range shares, are the most frequent (about 2.4 % of boxes each)"
               if paper_protocol else
               ". For tools that is one of wood's ten slots, which are about equally "
               "frequent: which of them wins, and with it Frequent's MAE (a light tool slides "
               "far), changes from one dataset to the next. Compare the MAE column, not these "
               "ratios, with the paper's (docs/data.md, \"Tools\")")
            + "."]
  lines += ["", "Paper (top-1 / top-5 / top-10 / RMSE / MAE): "
            + "; ".join(f"{k} {'/'.join(str(v) for v in vals)}" for k, vals in PAPER.items()),
            "", f"Shape F1 (IoU > 0.5): {_with_interval(r['shape'], 'f1')}; box count exact "
            f"on {_with_interval(r['shape'], 'count_exact')} % of tools; paper {PAPER_F1}."
            + (f" With the fit (+Fit's boxes): {_with_interval(r['shape_fit'], 'f1')}."
               if r.get("shape_fit") else ""), "",
            f"![decomposed test tools]({stem}_decomposition.png)", ""]
  if r.get("rerun"):
    lines += ["## +Sample and τ on the test tools (a diagnostic, not a choice)", "",
              "Each +Sample row's selection at every τ (the candidates are simulated once), "
              "and the same candidates picked by an oracle (the sample with the least slot "
              "error). τ is not chosen here, on the test tools: the tools preset's τ = "
              f"{PRESET_TAU} was chosen on 200 tools of another seed, none trained on, by "
              "density RMSE (`tool_fill_study/tau_choice/`)."]
    # the sweeps exist where the rerun evaluated with eval.studies (tools_rerun/run.py)
    at = r["rerun"].get("prior_sweeps", {}).get("PPD+Sample", {}).get(str(PRESET_TAU))
    if at:
      lines += [f"At τ = {PRESET_TAU} the test tools read PPD (full)+Sample top-1 "
                f"{at['top1']:.1f}, top-5 {at['top5']:.1f}, top-10 {at['top10']:.1f}, RMSE "
                f"{at['rmse']:.1f}, MAE {at['mae']:.1f} mm (the table above: τ = 0, the "
                "paper's rule)."]
    lines += [""] + prior_sweep_md(r["rerun"].get("prior_sweeps", {})) + [""]
    picks = {k.replace("PPD", "PPD (full)"): v
             for k, v in r["rerun"].get("oracle_pick", {}).items()}
    lines += oracle_pick_md({"table2": rows, "oracle_pick": picks}) + [""]
  lines += ["Fine-tuning on the tools (validation every 50 steps; the joint stage starts where "
            "the density loss appears):", "",
            f"![learning curves]({stem}_learning_curves.png)", "",
            "## Steps (wall time)", ""] + pipeline_steps.steps_md(r) + [""]
  return "\n".join(lines)


def names(config) -> tuple[str, str]:
  """(results' stem under experiments/results, the shipped model's folder under assets) of
  a tools preset: the paper's protocol and the realistic tools ship apart."""
  if tool_generation.protocol(config.data) == "paper":
    return "tools_paper", "tools_paper_model"
  return "tools", "tools_model"


def write_all(pipe, results_dir: str, assets_dir: str, command: str) -> dict:
  os.makedirs(results_dir, exist_ok=True)
  stem, model_name = names(pipe.config)
  r = collect(pipe)
  model_dir = os.path.join(assets_dir, model_name)
  checkpoints.export(pipe.workdir("full"), model_dir)
  figure(pipe, os.path.join(results_dir, f"{stem}_decomposition.png"), model_dir)
  plots.plot_variant_curves({v: os.path.join(pipe.workdir(v), "metrics.jsonl")
                             for v in pipe.variants},
                            os.path.join(results_dir, f"{stem}_learning_curves.png"))
  r["command"] = command
  r["protocol"] = tool_generation.protocol(pipe.config.data)
  text = markdown(r, command, stem)
  # Table 3 under the name the checks read ("table3"), the learned boxes' F1 and the commit
  # beside it (tools.json, written before, keeps "rows")
  saved = dict(r)
  if stem != "tools":
    saved = {"table3": saved.pop("rows"), "f1": r["shape"]["f1"],
             "commit": _git_state(results_dir)[0], **saved}
  path = os.path.join(results_dir, f"{stem}.json")
  with open(path, "w") as f:
    json.dump(saved, f, indent=1)
  key = "table3" if stem != "tools" else "rows"
  write_provenance(path, command=command, config=pipe.config, headlines={
      **row_headlines(saved[key], key, ("PPD (full)", "PPD (full)+Sample"), ("top1", "rmse")),
      "shape F1 (learned boxes)": "shape/f1"})
  with open(os.path.join(results_dir, f"{stem}.md"), "w") as f:
    f.write(text)
  print(f"wrote {results_dir}/{stem}.md, {stem}.json, {stem}_decomposition.png; model in "
        f"{model_dir}", flush=True)
  return r
