"""The full model on the whole test split, added to blocks.json / blocks.md.

`ppdjax.reproduce blocks` evaluates the full model on the whole test split by default; run
with `--max_objects=N` (e.g. 512, with the +Joint and true-box studies), this adds a
separate evaluation of every test object
(`python -m ppdjax.evaluate ... --out=DIR`, the command in its results.json) as
blocks.json's "whole_split", which the targets then read, and rewrites blocks.md:

    python experiments/blocks_whole_split/run.py --eval=DIR --machine="one NVIDIA H100 80GB HBM3" \
        --data_command="python -m ppdjax.generate ..."

The evaluation's results.md, results.json and confusion.png are copied to
RESULTS/blocks_whole_split/, and its kept per-object records (`--keep_records`:
partial/records.npz and settings.json) if it has them.
"""

import json
import os
import shutil

from absl import app, flags

from ppdjax.reproduce import blocks_common as common
from ppdjax.reproduce import blocks_report

from ppdjax.eval import partial

_EVAL = flags.DEFINE_string("eval", None, "The whole-split evaluation's output folder.",
                            required=True)
_RESULTS = flags.DEFINE_string("results", "experiments/results", "Where blocks.json is.")
_DATA_COMMAND = flags.DEFINE_string("data_command", "", "The command that made the dataset it "
                                    "read, when not the pipeline's own.")
_MACHINE = flags.DEFINE_string("machine", None, "The machine it ran on, for the README.",
                               required=True)


def main(argv):
  del argv
  full = common.read_evaluation(_EVAL.value)
  blocks_path = os.path.join(_RESULTS.value, "blocks.json")
  with open(blocks_path) as f:
    r = json.load(f)
  if full["split"] != "test" or full["objects"] < 1000:
    raise app.UsageError(f"{_EVAL.value} evaluated {full['objects']} objects of {full['split']!r}: "
                         "not the whole test split")
  out = os.path.join(_RESULTS.value, "blocks_whole_split")
  common.copy_evaluation(_EVAL.value, out)
  kept = os.path.join(_EVAL.value, "partial")
  if os.path.exists(os.path.join(kept, partial.RECORDS_FILE)):
    os.makedirs(os.path.join(out, "partial"), exist_ok=True)
    for name in (partial.RECORDS_FILE, "settings.json"):
      shutil.copyfile(os.path.join(kept, name), os.path.join(out, "partial", name))
  records = os.path.exists(os.path.join(out, "partial", partial.RECORDS_FILE))
  with open(os.path.join(out, "README.md"), "w") as f:
    f.write(f"# The full model on the whole test split ({full['objects']} objects)\n\n"
            f"Machine: {_MACHINE.value}. Commands:\n\n```\n"
            + (f"{_DATA_COMMAND.value}\n" if _DATA_COMMAND.value else "")
            + f"{full['command']}\n```\n\n"
            "Tables in `results.md`; blocks.json's \"whole_split\" and blocks.md's targets "
            "read them (`python experiments/blocks_whole_split.py`).\n"
            + ("\nThe per-object records (`partial/records.npz`, read by "
               "`ppdjax.eval.partial.saved_records`) let the tables be read again without a "
               "GPU, e.g. `experiments/selection_horizon_study.py`.\n" if records else ""))
  command = ((_DATA_COMMAND.value + "\n") if _DATA_COMMAND.value else "") + full["command"]
  r["whole_split"] = blocks_report.whole_split(r, full, command)
  r["whole_split"]["machine"] = _MACHINE.value
  common.write(_RESULTS.value, "blocks", r, blocks_report.report_md(r, r["command"]))
  print(f"and {out}")


if __name__ == "__main__":
  app.run(main)
