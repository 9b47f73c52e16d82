"""Paper Table 2 on block towers: baselines, the three ablations, full, +Sample, +Refine.

  python experiments/table2.py --config=ppdjax/configs/tiny.py --data=out/blocks_tiny \
      --root=out/blocks_runs --out=experiments/results/tiny

Trains (or resumes) the full model and the no-trajectory, no-image and no-voxels
ablations into ROOT/<variant>, evaluates each on the test split and writes
OUT/table2.json and OUT/table2.md beside the paper's numbers.
"""

from __future__ import annotations

import sys

from absl import app, flags

import blocks_common as common
from ppdjax.infer import markdown, tables

common.define_flags()
flags.DEFINE_list("variants", list(common.VARIANTS), "Model variants to include.")
FLAGS = flags.FLAGS

PAPER = tables.PAPER_TABLE2


def table2(config, data_dir, root, variants, samples, refine, max_objects=0):
  """(rows, observes, f1): Table 2 rows from the variants' evaluations."""
  rows, observes = {}, {}
  full = None
  for v in variants:
    res = common.ensure_evaluated(config, data_dir, root, v, samples=samples,
                                  refine=refine and v == "full", max_objects=max_objects)
    name = common.VARIANTS[v][1]
    m = res["model"]
    if v == "full":
      full = res
      for b in tables.BASELINES:
        rows[b] = res["table2"][b]
      observes.update({"Frequent": (False, False), "Nearest": (False, True),
                       "Oracle": (True, False)})
    for suffix, key in (("", "PPD"), ("+Sample", "PPD+Sample"),
                        ("+Sample+Refine", "PPD+Sample+Refine")):
      if key in res["table2"] and (v == "full" or not suffix):
        rows[name + suffix] = res["table2"][key]
        observes[name + suffix] = (m["use_image"], m["use_trajectory"])
  order = list(tables.BASELINES) + [common.VARIANTS[v][1] for v in
                                       ("no_trajectory", "no_image", "no_voxels", "full")]
  ranked = [r for base in order for r in rows if r.split("+")[0] == base]
  return {r: rows[r] for r in ranked}, observes, (full or {}).get("f1")


def main(argv):
  del argv
  config, samples, refine = common.evaluation_settings()
  rows, observes, f1 = table2(config, FLAGS.data, FLAGS.root, FLAGS.variants, samples, refine,
                              FLAGS.max_objects)
  command = "python experiments/table2.py " + " ".join(sys.argv[1:])
  md = [f"# Table 2 ({config.name} preset): physical parameters of block towers", "",
        "```", command, "```", "",
        f"Test split, {samples} density samples" + (", LM refinement" if refine else "")
        + ". Density top-k in %, RMSE in slots (×100 kg/m³), trajectory MAE in mm"
        " (the paper's units are not stated)."
        + (f" Shape F1 of the full model: {f1:.1f} (paper {tables.PAPER_SHAPE_F1})."
           if f1 is not None else ""),
        ""]
  md += markdown.table2_md(rows, observes)
  md += ["", "Paper:", "", "| Method | Top 1 | Top 5 | Top 10 | RMSE | MAE |",
         "|---|--:|--:|--:|--:|--:|"]
  md += [f"| {k} | " + " | ".join(str(x) for x in v) + " |" for k, v in PAPER.items()]
  common.write(FLAGS.out, "table2", {"command": command, "samples": samples, "refine": refine,
                                     "table2": rows, "f1": f1, "paper": PAPER},
               "\n".join(md) + "\n")


if __name__ == "__main__":
  app.run(main)
