"""The full tools model evaluated again on the whole tools test split, its rows replacing
the full model's in tools.json / tools.md (the ablations' rows and the run's logs stay).

`ppdjax.reproduce tools` evaluates each model as it trains it; after a change to the
evaluation (the +Sample ranking fix of 2026-11-25, say), the shipped model is evaluated
again on the same test tools (the dataset remade from the preset's seed) and merged here:

    python -m ppdjax.reproduce tools --step=generate:tools --root=ROOT
    python -m ppdjax.evaluate --workdir=assets/tools_model --data=ROOT/data --split=test \
        --config.eval.true_shapes=True --config.eval.studies=True --out=DIR
    python experiments/tools_rerun/run.py --eval=DIR --machine="one NVIDIA H100 80GB HBM3"

The evaluation's results.md, results.json and confusion.png are copied to
RESULTS/tools_rerun/.
"""

import json
import os

from absl import app, flags

from ppdjax.reproduce import blocks_common as common
from ppdjax.reproduce import tools_report

_EVAL = flags.DEFINE_string("eval", None, "The evaluation's output folder.", required=True)
_RESULTS = flags.DEFINE_string("results", "experiments/results", "Where tools.json is.")
_MACHINE = flags.DEFINE_string("machine", None, "The machine it ran on.", required=True)
DATA_COMMAND = "python -m ppdjax.reproduce tools --step=generate:tools"
FULL_ROWS = {"Frequent": "Frequent", "Nearest": "Nearest", "Oracle": "Oracle",
             "PPD": "PPD (full)", "PPD+Sample": "PPD (full)+Sample"}


def main(argv):
  del argv
  full = common.read_evaluation(_EVAL.value)
  path = os.path.join(_RESULTS.value, "tools.json")
  with open(path) as f:
    r = json.load(f)
  if full["split"] != "test" or full["objects"] != r["objects"]:
    raise app.UsageError(f"{_EVAL.value} evaluated {full['objects']} objects of "
                         f"{full['split']!r}; "
                         f"tools.json's rows are over the {r['objects']} test tools")
  for name, row in full["table2"].items():  # the +Fit and true-box rows keep their names
    r["rows"][FULL_ROWS.get(name, name.replace("PPD", "PPD (full)"))] = row
  r["shape"], r["shape_fit"] = full["shape"], full.get("shape_fit")
  r["rerun"] = {"command": f"{DATA_COMMAND}\n{full['command']}", "machine": _MACHINE.value,
                "prior_weight": full["prior_weight"], "prior_sweeps": full["prior_sweeps"],
                "oracle_pick": full["oracle_pick"], "seconds": full["seconds"]}
  out = os.path.join(_RESULTS.value, "tools_rerun")
  common.copy_evaluation(_EVAL.value, out)
  common.write(_RESULTS.value, "tools", r, tools_report.markdown(r, r["command"]))
  print(f"and {out}")


if __name__ == "__main__":
  app.run(main)
