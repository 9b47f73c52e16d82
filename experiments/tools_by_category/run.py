"""Table 3 by tool category, from an evaluation's kept per-object records (CPU only).

  python experiments/tools_by_category/run.py \
      --records=experiments/results/tools_runs/eval_full/records \
      --results=experiments/results/tools_runs/eval_full/results.json \
      --out=experiments/results/tools_by_category

A tool is a pure function of the dataset's seed and its index (`tools.sample_tool`) and
its split of the index alone (`storage.split_of`), so the records' objects are the test
tools in index order, each with its `configs_per_tool` configurations in a row
(`tool_generation.generate_shard`).
The script rebuilds each test tool's category and, before trusting that order, checks it:
every record's true box count, and for the first configuration of each tool (the tool's own
slots) its true slots, must equal those of the rebuilt tool's ground-truth boxes
(`mesh_boxes.primitives_from_mesh`; about 0.5 s a tool on a CPU). A tool whose generation fell
back to another draw (its simulation diverged, `tool_generation.ATTEMPTS`) fails the check
and is reported, not guessed. Then `tables.summarize` runs on each category's objects, with
intervals over its tools. Writes OUT/results.md, results.json and by_category.png.
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import app, flags
from tqdm import tqdm

from ppdjax.configs import tools as tools_preset
from ppdjax.conventions import density_to_slot
from ppdjax.dataset import storage, tools
from ppdjax.dataset.mesh_boxes import primitives_from_mesh
from ppdjax.eval import partial
from ppdjax.report import tables
from ppdjax.report.markdown import with_ci

FLAGS = flags.FLAGS

ROWS = ("PPD", "PPD+Sample", "Nearest")


def test_tools(num_tools: int, fractions) -> np.ndarray:
  """Indices of the test split's tools, in the dataset's order (the split hashes the
  index: it is the same for every seed)."""
  ids = np.arange(num_tools)
  return ids[storage.split_of(ids, tuple(fractions)) == 2]


def tool_truth(seed: int, index: int) -> tuple[str, np.ndarray]:
  """(category, true slots of its boxes bottom to top, -1 padded) of attempt 0 of tool
  `index`, as the dataset's first configuration labels it."""
  tool = tools.sample_tool(seed, index)
  prims, _ = primitives_from_mesh(list(tool.parts), densities=tool.densities)
  slots = np.where(np.asarray(prims.valid), density_to_slot(np.asarray(prims.density)), -1)
  return tool.category, np.asarray(slots)


def check_order(rec: dict, truths: list, configs: int) -> list[int]:
  """Positions (in `truths`) of tools whose records do not match the rebuilt tool."""
  true_slot = np.asarray(rec[("true_slot",)]).reshape(len(truths), configs, -1)
  valid = np.asarray(rec[("true_valid",)]).reshape(len(truths), configs, -1)
  bad = []
  for t, (_, slots) in enumerate(truths):
    k = int((slots >= 0).sum())
    same_count = bool((valid[t].sum(-1) == k).all())
    same_slots = same_count and np.array_equal(true_slot[t, 0, :k], slots[:k])
    if not same_slots:
      bad.append(t)
  return bad


def by_category(rec: dict, categories: np.ndarray, tool_ids: np.ndarray, switches: dict,
                keep: np.ndarray) -> dict:
  """summarize() of each category's objects (those in `keep`), intervals over tools."""
  out = {}
  for name in tools.CATEGORIES:
    mask = keep & (categories == name)
    if not mask.any():
      continue
    sub = {k: np.asarray(v)[mask] for k, v in rec.items()}
    res = tables.summarize(switches, sub, geometries=tool_ids[mask])
    out[name] = {"objects": int(mask.sum()), "tools": int(len(np.unique(tool_ids[mask]))),
                 "f1": res["f1"], "f1_ci95": res["shape"]["f1_ci95"],
                 "rows": {r: {k: res["table2"][r].get(k) for k in
                              ("top1", "top5", "top10", "rmse", "mae", "ci95")}
                          for r in ROWS if r in res["table2"]}}
  return out


def markdown(table: dict, command: str, total: int, dropped: int) -> str:
  lines = ["# Table 3 by tool category", "", "```", command, "```", "",
           f"{total} test objects; {dropped} left out (tools whose records did not match the "
           "rebuilt tool). Intervals: 95 % bootstrap over the category's tools. Top-k in %, "
           "RMSE in slots, MAE in mm.", "",
           "| category | tools | objects | shape F1 | PPD top-1 | PPD top-5 | PPD RMSE | "
           "PPD+Sample top-1 | PPD+Sample RMSE | PPD+Sample MAE | Nearest top-1 |",
           "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
  for name, c in table.items():
    ppd, smp, nn = (c["rows"].get(r, {}) for r in ROWS)
    f1 = with_ci({"f1": c["f1"], "ci95": {"f1": c["f1_ci95"]}}, "f1")
    lines.append(
        f"| {name} | {c['tools']} | {c['objects']} | {f1} | {with_ci(ppd, 'top1')} | "
        f"{ppd['top5']:.1f} | {with_ci(ppd, 'rmse')} | {smp['top1']:.1f} | "
        f"{smp['rmse']:.1f} | {smp['mae']:.1f} | {nn['top1']:.1f} |")
  return "\n".join(lines) + "\n"


def figure(table: dict, path: str) -> None:
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  names = list(table)
  fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
  panels = (("PPD top-1 (%)", lambda c: (c["rows"]["PPD"]["top1"],
                                         c["rows"]["PPD"]["ci95"].get("top1"))),
            ("PPD density RMSE (slots)", lambda c: (c["rows"]["PPD"]["rmse"],
                                                   c["rows"]["PPD"]["ci95"].get("rmse"))),
            ("shape F1 (%)", lambda c: (c["f1"], c["f1_ci95"])))
  x = np.arange(len(names))
  for ax, (title, get) in zip(axes, panels):
    vals = [get(table[n]) for n in names]
    mid = np.asarray([v for v, _ in vals])
    lo = np.asarray([v - (ci[0] if ci else v) for v, ci in vals])
    hi = np.asarray([(ci[1] if ci else v) - v for v, ci in vals])
    ax.bar(x, mid, yerr=[lo, hi], color="#6a8caf", capsize=3)
    ax.set_xticks(x, names, rotation=40, ha="right")
    ax.set_title(title)
  fig.suptitle("Tools test split by category (95 % intervals over tools)")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_string("records", None, "A folder of kept evaluation records.", required=True)
  flags.DEFINE_string("results", None, "The same evaluation's results.json.", required=True)
  flags.DEFINE_string("out", None, "Output folder.", required=True)
  flags.DEFINE_string("size", "paper", "The tools preset's size of the data.")


def main(argv):
  del argv
  for path in (FLAGS.records, FLAGS.results):
    if not os.path.exists(path):
      raise SystemExit(f"not found: {path}")
  preset = tools_preset.get_config(FLAGS.size)
  data, seed = preset.data, preset.seed
  configs = int(data.configs_per_tool)
  rec = partial.saved_records(FLAGS.records)
  with open(FLAGS.results) as f:
    switches = json.load(f)["model"]
  ids = test_tools(data.num_tools, data.split_fractions)
  n = len(rec[("blocks",)])
  if n != len(ids) * configs:
    raise SystemExit(f"{n} records, but the preset's test split has {len(ids)} tools x "
                     f"{configs} configurations = {len(ids) * configs} objects: records of "
                     "another dataset or a part of the split")
  truths = [tool_truth(seed, int(i)) for i in tqdm(ids, desc="rebuilding test tools")]
  bad = check_order(rec, truths, configs)
  if len(bad) > 0.05 * len(ids):
    raise SystemExit(f"{len(bad)} of {len(ids)} tools do not match their records: the "
                     "records are not this dataset's test split in order")
  tool_ids = np.repeat(ids, configs)
  categories = np.repeat(np.asarray([c for c, _ in truths]), configs)
  keep = ~np.isin(tool_ids, ids[bad])
  table = by_category(rec, categories, tool_ids, switches, keep)
  os.makedirs(FLAGS.out, exist_ok=True)
  command = ("python experiments/tools_by_category/run.py " + f"--records={FLAGS.records} "
             f"--results={FLAGS.results} --out={FLAGS.out}")
  with open(os.path.join(FLAGS.out, "results.json"), "w") as f:
    json.dump({"command": command, "objects": n, "left_out_tools": [int(ids[b]) for b in bad],
               "categories": table}, f, indent=1)
  md = markdown(table, command, n, int((~keep).sum()))
  with open(os.path.join(FLAGS.out, "results.md"), "w") as f:
    f.write(md)
  figure(table, os.path.join(FLAGS.out, "by_category.png"))
  print(md)


if __name__ == "__main__":
  define_flags()
  app.run(main)
