"""Paper Table 5: density RMSE by number of blocks, by what the model observes.

  python experiments/table5.py --config=ppdjax/configs/tiny.py --data=out/blocks_tiny \
      --root=out/blocks_runs --out=experiments/results/tiny

Texture: the model without trajectories; Physics: the model without the image; Texture +
Physics: the full model, plain and with +Sample. Reuses table2.py's evaluations.
"""

from __future__ import annotations

import sys

from absl import app, flags

import blocks_common as common
from ppdjax.infer import markdown, tables

common.define_flags()
FLAGS = flags.FLAGS

PAPER = tables.PAPER_TABLE5
ROWS = (("Texture", "no_trajectory", "PPD"), ("Physics", "no_image", "PPD"),
        ("Texture + Physics", "full", "PPD"),
        ("Texture + Physics (+Sample)", "full", "PPD+Sample"),
        ("Texture + Physics (+Sample+Refine)", "full", "PPD+Sample+Refine"))


def main(argv):
  del argv
  config, samples, refine = common.evaluation_settings()
  table = {}
  for name, variant, row in ROWS:
    res = common.ensure_evaluated(config, FLAGS.data, FLAGS.root, variant, samples=samples,
                                  refine=refine and variant == "full",
                                  max_objects=FLAGS.max_objects)
    if row in res["table5"]:
      table[name] = res["table5"][row]
  command = "python experiments/table5.py " + " ".join(sys.argv[1:])
  md = [f"# Table 5 ({config.name} preset): density RMSE (slots) by number of blocks", "",
        "```", command, "```", ""]
  md += markdown.table5_md(table)
  md += ["", "Paper:", "", "| | 2 blocks | 3 blocks | 4 blocks | 5 blocks | Overall |",
         "|---|--:|--:|--:|--:|--:|"]
  md += [f"| {k} | " + " | ".join(str(x) for x in v) + " |" for k, v in PAPER.items()]
  common.write(FLAGS.out, "table5", {"command": command, "table5": table, "paper": PAPER},
               "\n".join(md) + "\n")


if __name__ == "__main__":
  app.run(main)
