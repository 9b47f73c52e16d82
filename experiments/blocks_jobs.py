"""Runs experiments/blocks.py's steps side by side (`--jobs=N`), each in its own process.

A step starts as soon as the steps it needs are done, at most N at once, in the order of
the step list: e.g. an ablation trains while the full model's evaluation compiles (minutes
of CPU in which the accelerator would sit idle) or samples. Each child is
`blocks.py ARGS --step=NAME` (--jobs acts only with --step=all), so it resumes exactly as a
step run by hand does; its output goes to ROOT/logs/NAME.log. Children share the
machine's devices and take accelerator memory as they need it
(XLA_PYTHON_CLIENT_PREALLOCATE=false unless the caller set it), so N is bounded by memory:
two trainings of the paper preset side by side held 35 GB of an 80 GB H100.

If a step fails, the steps that need it are not started, the running ones finish, and
the scheduler exits non-zero after naming the failed step and the end of its log.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

POLL_S = 2.0
LOG_TAIL = 3000


def _child_env() -> dict[str, str]:
  env = dict(os.environ)
  if "XLA_PYTHON_CLIENT_MEM_FRACTION" not in env:
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
  env.setdefault("PYTHONUNBUFFERED", "1")
  return env


def _tail(path: str) -> str:
  with open(path, errors="replace") as f:
    return f.read()[-LOG_TAIL:]


def run(names: Sequence[str], needs: Callable[[str], Sequence[str]],
        done: Callable[[str], bool], jobs: int, argv: Sequence[str], log_dir: str) -> int:
  """Runs every step of `names` not yet done; returns 0 when all finished, else 1.

  needs(name): the steps `name` waits for; done(name): whether it is complete on disk;
  argv: blocks.py's own command line (script first), to which each child adds its step.
  """
  if jobs < 1:
    raise ValueError(f"--jobs must be at least 1, got {jobs}")
  unknown = {d for n in names for d in needs(n)} - set(names)
  if unknown:
    raise ValueError(f"steps need unknown steps: {sorted(unknown)}")
  os.makedirs(log_dir, exist_ok=True)
  pending = [n for n in names if n == "report" or not done(n)]
  finished = {n for n in names if n not in pending}
  failed: set[str] = set()
  running: dict[str, tuple[subprocess.Popen, float, object]] = {}
  t0 = time.perf_counter()

  def blocked(name: str) -> bool:  # something it needs failed or will never run
    return any(d in failed or (d not in finished and d not in pending and d not in running)
               for d in needs(name))

  while pending or running:
    for name in list(pending):
      if blocked(name):
        pending.remove(name)
        failed.add(name)
        print(f"-- {name}: not started ({', '.join(d for d in needs(name) if d in failed)} "
              "failed)", flush=True)
      elif len(running) < jobs and all(d in finished for d in needs(name)):
        pending.remove(name)
        log = open(os.path.join(log_dir, name.replace(":", "_") + ".log"), "w")
        cmd = [sys.executable, *argv, f"--step={name}"]
        running[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                          env=_child_env()), time.perf_counter(), log)
        print(f"-- {name}: started ({len(running)} running, "
              f"{time.perf_counter() - t0:.0f} s in)", flush=True)
    time.sleep(POLL_S)
    for name, (proc, start, log) in list(running.items()):
      if proc.poll() is None:
        continue
      del running[name]
      log.close()
      seconds = time.perf_counter() - start
      if proc.returncode == 0 and (name == "report" or done(name)):
        finished.add(name)
        print(f"-- {name}: done in {seconds:.0f} s ({time.perf_counter() - t0:.0f} s in)",
              flush=True)
      else:
        failed.add(name)
        print(f"-- {name}: FAILED (exit {proc.returncode}) after {seconds:.0f} s; end of "
              f"{log.name}:\n{_tail(log.name)}", flush=True)
  print(f"-- all steps: {time.perf_counter() - t0:.0f} s wall, {jobs} at once"
        + (f"; failed or not started: {', '.join(sorted(failed))}" if failed else ""),
        flush=True)
  return 1 if failed else 0
