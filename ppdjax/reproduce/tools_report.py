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
from ppdjax.conventions import TIMESTEP, slot_to_density
from ppdjax.configs import tools as tools_preset
from ppdjax.dataset import storage, tool_generation, tools
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
HEADLINE_ROW = "PPD (full)+Sample"  # what `decompose` returns with the shipped settings


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
          # by material of the true box, each row; by the tool's category, the full model's
          "by_material_rows": {_row_name(k): v for k, v in full.get("by_material", {}).items()},
          **({"by_category": by_category(pipe.data, full)} if "per_object" in full else {}),
          "objects": full["objects"], "frequent_slot": full.get("frequent_slot"),
          **{k: full.get(k) for k in tables.INTERVAL_KEYS},
          "data_kind": "tools",  # also for evaluations from before they recorded it
          "configs_per_tool": tool_generation.configs_per_tool(pipe.config.data),
          "push_force": tool_generation.push_force(pipe.config.data),
          "samples": full["samples"], "mae_units": full.get("mae_units", "mm"),
          **pipeline_steps.read_log(pipe.root)}


def _row_name(name: str) -> str:
  """The full model's evaluation row under Table 3's name ("PPD+Sample" -> "PPD (full)+Sample")."""
  return name.replace("PPD", "PPD (full)", 1)


def by_category(data_dir: str, full: dict) -> dict:
  """The full model's PPD and +Sample rows by the test tools' category (top-1 %, RMSE
  slots, boxes), from its per-object hits; the categories recorded by the dataset
  ("category" ids into `tools.CATEGORIES`), in the order the evaluation read the test
  split (its first `objects`)."""
  test = storage.open_dataset(data_dir, "test")
  if "category" not in test.sample_keys:
    return {}
  ids = test.take(np.arange(full["objects"]), keys=("category",))["category"]
  out = {}
  for row, per in full["per_object"].items():
    hits, sq, count = (np.asarray(per[k]) for k in ("top1", "sq_err", "count"))
    out[_row_name(row)] = {
        name: {"boxes": int(count[ids == c].sum()),
               "top1": 100.0 * float(hits[ids == c].sum() / max(count[ids == c].sum(), 1)),
               "rmse": float(np.sqrt(sq[ids == c].sum() / max(count[ids == c].sum(), 1)))}
        for c, name in enumerate(tools.CATEGORIES) if np.any(ids == c)}
  return out


SLOW = 0.05  # m/s: under 1.7 mm between two frames of a 30 fps camera (a tracker's error)


def start_speeds(data_dir: str) -> dict:
  """How fast the test tools start under each push (m/s, the centre's speed over the
  steps just after the push): percentiles, the share starting slower than SLOW (not
  measurably), and how far they go (m)."""
  test = storage.open_dataset(data_dir, "test")
  traj = test.take(np.arange(len(test)), keys=("trajectories",))["trajectories"]
  pos = np.asarray(traj[..., :3], np.float64)
  speed = np.linalg.norm(pos[..., 3, :] - pos[..., 1, :], axis=-1) / (2 * TIMESTEP)
  travel = np.linalg.norm(pos[..., -1, :] - pos[..., 0, :], axis=-1)
  names = ("p1", "p10", "p50", "p90", "p99")
  q = lambda x: dict(zip(names, map(float, np.percentile(x, [1, 10, 50, 90, 99]))))  # noqa: E731
  return {"percentiles": q(speed), "travel_m": q(travel),
          "slow_fraction": 100.0 * float(np.mean(speed < SLOW)), "rollouts": int(speed.size)}


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
  lines += realistic_md(r)
  lines += ["Fine-tuning on the tools (validation every 50 steps; the joint stage starts where "
            "the density loss appears):", "",
            f"![learning curves]({stem}_learning_curves.png)", "",
            "## Steps (wall time)", ""] + pipeline_steps.steps_md(r) + [""]
  return "\n".join(lines)


def realistic_md(r: dict) -> list[str]:
  """The realistic benchmark's breakdowns: by material, metal's range confusions, by
  category, and how fast the tools start (nothing for reports without them)."""
  lines = []
  if r.get("floor"):
    fl, head = r["floor"], r["rows"].get(HEADLINE_ROW, {})
    reader = fl["reader"]
    lines += ["## The floor: a Bayes reader of the voxels and the motion", "",
              f"On the first {fl['tools']} test tools ({fl['objects']} objects, {fl['boxes']} "
              "boxes; `ppdjax.eval.tool_floor`): the generator's hidden dimensions sampled "
              f"consistently with the voxels ({reader['geometries']} samples a tool), the "
              f"trajectories tracked at {1 / reader['frame_seconds']:.0f} frames a second with "
              f"{reader['sigma_position_m'] * 1e3:g} mm and {reader['sigma_rotation_deg']:g}° "
              "of noise, each piece's density read by Bayes over every slot its plausible "
              "materials allow (the image unused).", "",
              "| reader | top-1 | RMSE |", "|---|--:|--:|",
              f"| floor, posterior mode | {fl['top1']:.1f} | {fl['rmse']:.1f} |",
              f"| floor, posterior mean | – | {fl['rmse_mean']:.1f} |"]
    if head:
      lines.append(f"| {HEADLINE_ROW} (the whole test split) | {head['top1']:.1f} | "
                   f"{head['rmse']:.1f} |")
    lines += ["", "By material (floor, mode): " + ", ".join(
        f"{m} {v['top1']:.1f} / {v['rmse']:.1f} ({v['boxes']} boxes)"
        for m, v in fl["by_material"].items()) + ".", ""]
  rows = r.get("by_material_rows") or {}
  if rows:
    materials = [m for m in next(iter(rows.values())) if m != "range_confusions"]
    lines += ["## By material of the true box (top-1 % / RMSE slots)", "",
              "| Method | " + " | ".join(f"{m} ({rows[next(iter(rows))][m]['boxes']})"
                                         for m in materials) + " | metal range confusions |",
              "|---|" + "--:|" * (len(materials) + 1)]
    for name, per in rows.items():
      lines.append(f"| {name} | " + " | ".join(
          f"{per[m]['top1']:.1f} / {per[m]['rmse']:.1f}" if m in per else "–"
          for m in materials) + f" | {per['range_confusions']:.1f} % |")
    lines += ["", "Metal takes two slot ranges (aluminium-like 2,100-3,500 and steel-like "
              "7,100-10,000 kg/m³) that look alike; a range confusion is a metal box read in "
              "the other range, as a share of all boxes.", ""]
  if r.get("by_category"):
    cats = list(next(iter(r["by_category"].values())))
    lines += ["## By category (top-1 % / RMSE slots; boxes)", "",
              "| Method | " + " | ".join(cats) + " |", "|---|" + "--:|" * len(cats)]
    for name, per in r["by_category"].items():
      lines.append(f"| {name} | " + " | ".join(
          f"{per[c]['top1']:.1f} / {per[c]['rmse']:.1f} ({per[c]['boxes']})" for c in cats)
          + " |")
    lines.append("")
  if r.get("speeds"):
    s = r["speeds"]
    lines += ["## How fast the test tools start", "",
              f"Pushes {r.get('push', 'fixed')}"
              + (" (each tool's force scales with its volume: a tool's start speed reads "
                 "its mean density)" if r.get("push") == "by_volume" else "")
              + f"; the centre's speed just after each push over {s['rollouts']} rollouts, "
              "m/s: " + ", ".join(f"{k} {v:.3g}" for k, v in s["percentiles"].items())
              + f"; {s['slow_fraction']:.1f} % start slower than {SLOW:g} m/s (under 1.7 mm "
              "between two frames of a 30 fps camera); distance travelled in 256 steps, m: "
              + ", ".join(f"{k} {v:.3g}" for k, v in s["travel_m"].items()) + ".", ""]
  return lines


def names(config) -> tuple[str, str]:
  """(results' stem under experiments/results, the shipped model's folder under assets) of
  a tools preset: the paper's protocol and the realistic tools ship apart."""
  if tool_generation.protocol(config.data) == "paper":
    return "tools_paper", "tools_paper_model"
  if tool_generation.materials_mode(config.data) == "plausible":  # the mended labels
    return "tools_realistic", "tools_model"
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
  if stem == "tools_realistic":
    with open(pipe.floor_file) as f:
      r["floor"] = json.load(f)
    r["speeds"] = start_speeds(pipe.data)
    r["push"] = tool_generation.push_mode(pipe.config.data)
    headline = r["by_material_rows"].get(HEADLINE_ROW, {})
    r["by_material"] = {m: {k: v[k] for k in ("top1", "rmse", "boxes")}
                        for m, v in headline.items() if isinstance(v, dict)}
    r["metal_range_confusions"] = headline.get("range_confusions")
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
