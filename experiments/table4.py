"""Paper Table 4: best-of-N sampling through the physics engine, with and without the network.

  python experiments/table4.py --config=ppdjax/configs/tiny.py --data=out/blocks_tiny \
      --root=out/blocks_runs --out=experiments/results/tiny

Rows: Sample Phys.+Shape (random tower shapes and densities), Sample Phys. (true shape,
uniform densities) and PPD (the full model's density samples, candidate 0 its arg-max),
each the trajectory MAE (mm) of the candidate with the smallest trajectory distance
among the first N. Reuses the full model's evaluation when table2.py made one.
"""

from __future__ import annotations

import sys

from absl import app, flags

import blocks_common as common
from ppdjax.infer import markdown, tables

common.define_flags()
FLAGS = flags.FLAGS


def main(argv):
  del argv
  config, samples, refine = common.evaluation_settings()
  res = common.ensure_evaluated(config, FLAGS.data, FLAGS.root, "full", samples=samples,
                                refine=refine, max_objects=FLAGS.max_objects)
  command = "python experiments/table4.py " + " ".join(sys.argv[1:])
  md = [f"# Table 4 ({config.name} preset): best of N physics samples", "", "```", command,
        "```", "", f"{res.get('table4_evaluated', res['objects'])} test objects; trajectory MAE "
        "in mm.", ""]
  md += markdown.table4_md(res["table4"])
  md += ["", "Paper (1×/8×/64×/512×):", "", "| | 1× | 8× | 64× | 512× |", "|---|--:|--:|--:|--:|"]
  md += [f"| {k} | " + " | ".join(str(x) for x in v) + " |"
         for k, v in tables.PAPER_TABLE4.items()]
  common.write(FLAGS.out, "table4", {"command": command, "table4": res["table4"],
                                     "paper": tables.PAPER_TABLE4}, "\n".join(md) + "\n")


if __name__ == "__main__":
  app.run(main)
