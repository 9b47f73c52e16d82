"""`python -m ppdjax.reproduce blocks|tools|video [--list] [--step=...] [--jobs=N] ...`.

Each pipeline is a list of resumable steps (generate, train, evaluate, export, report; see
its module's docstring): `--list` prints what is done and what is left, `--step=next` runs
one, `--jobs=N` runs independent steps side by side. Results land in experiments/results/
with their provenance records.
"""

import importlib
import sys

from absl import app

PIPELINES = {"blocks": "the block towers: Tables 2, 4 and 5 (configs/paper.py)",
             "tools": "the tools: Table 3 (configs/tools.py)",
             "video": "the video towers: tracked trajectories (configs/video.py)"}


def main() -> None:
  if len(sys.argv) < 2 or sys.argv[1] not in PIPELINES:
    lines = [f"  {name:7s} {what}" for name, what in PIPELINES.items()]
    sys.exit("usage: python -m ppdjax.reproduce PIPELINE [flags]   (--helpfull: its flags)\n"
             + "\n".join(lines))
  name = sys.argv[1]
  pipeline = importlib.import_module(f"ppdjax.reproduce.{name}")
  # the steps' child processes run the same command line with --step=NAME
  sys.argv = ["-m", "ppdjax.reproduce", name, *sys.argv[2:]]
  app.run(pipeline.main)


if __name__ == "__main__":
  main()
