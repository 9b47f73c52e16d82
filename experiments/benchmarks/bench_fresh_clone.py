"""The README's two commands from a fresh clone, timed as a new user meets them.

  python experiments/benchmarks/bench_fresh_clone.py --steps=demo,test \
      [--front_door=experiments/results/bench_front_door.json]

Clones the repository's HEAD into a temporary folder and runs `make demo` (the install
included: the clone has no virtual environment) and then `make test` with empty
compilation caches (the clone's `.jax_cache`, and `~/.cache/ppdjax` moved aside for the
run), printing each command's output as it goes and its wall time at the end. Peer: none
(the budgets are absolute: 5 and 10 minutes on 2 cores). `--front_door` merges the
figures into that results file (`demo_fresh_clone_s`, `test_fresh_clone_s`).
"""

from __future__ import annotations

import datetime
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

from absl import app, flags

flags.DEFINE_list("steps", ["demo", "test"], "Which of the README's commands.")
flags.DEFINE_string("front_door", "", "Merge the figures into this results file.")
flags.DEFINE_string("python", "python3", "The interpreter `make` creates the venv with.")
FLAGS = flags.FLAGS
KEYS = {"demo": "demo_fresh_clone_s", "test": "test_fresh_clone_s"}


def main(argv):
  del argv
  root = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True,
                        text=True, check=True).stdout.strip()
  commit = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
  user_cache = os.path.expanduser("~/.cache/ppdjax")
  aside = user_cache + ".aside"
  seconds = {}
  with tempfile.TemporaryDirectory() as tmp:
    clone = os.path.join(tmp, "ppdjax")
    subprocess.run(["git", "clone", "-q", root, clone], check=True)
    moved = os.path.exists(user_cache)
    if moved:
      shutil.move(user_cache, aside)
    try:
      for step in FLAGS.steps:
        t0 = time.perf_counter()
        subprocess.run(["make", step, f"PYTHON={FLAGS.python}"], cwd=clone, check=True,
                       stdout=sys.stdout, stderr=sys.stderr)
        seconds[step] = time.perf_counter() - t0
        print(f"make {step}: {seconds[step]:.0f} s", flush=True)
    finally:
      if moved:
        shutil.rmtree(user_cache, ignore_errors=True)
        shutil.move(aside, user_cache)
  print({k: round(v) for k, v in seconds.items()}, "at", commit)
  if FLAGS.front_door:
    machine = f"{os.cpu_count()} CPU cores, no accelerator"
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    out = json.load(open(FLAGS.front_door)) if os.path.exists(FLAGS.front_door) else {}
    for step, s in seconds.items():
      out[KEYS[step]] = {"value": round(s, 1), "unit": "s", "machine": machine,
                         "date": datetime.date.today().isoformat(),
                         "command": command, "commit": commit}
    with open(FLAGS.front_door, "w") as f:
      json.dump(out, f, indent=1, sort_keys=True)


if __name__ == "__main__":
  app.run(main)
