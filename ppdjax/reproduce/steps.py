"""The step runner of the paper-scale pipelines (`python -m ppdjax.reproduce blocks|tools|video`).

A pipeline is a list of steps (name, done?, action) whose state lives only on disk, and
a `needs(name)` giving the steps each waits for. `run_steps` runs every step left, the
next one, or one by name; each call of a step is logged to ROOT/steps.jsonl (wall time,
start and end, device), which `read_log` sums for the reports.

With --jobs=N (`run_side_by_side`), a step starts as soon as the steps it needs are done,
at most N at once, in the order of the step list, each in its own process: e.g. an
ablation trains while the full model's evaluation compiles (minutes of CPU in which the
accelerator would sit idle) or samples. Each child is
`SCRIPT ARGS --step=NAME` (--jobs acts only with --step=all), so it resumes exactly as a
step run by hand does; its output goes to ROOT/logs/NAME.log. Children share the
machine's devices and take accelerator memory as they need it
(XLA_PYTHON_CLIENT_PREALLOCATE=false unless the caller set it), so N is bounded by memory:
two trainings of the paper preset side by side held 35 GB of an 80 GB H100.

If a step fails, the steps that need it are not started, the running ones finish, and
the scheduler exits non-zero after naming the failed step and the end of its log. A step
that ran out of accelerator memory beside others (its log ends with XLA's
RESOURCE_EXHAUSTED) is not a failure yet: it starts again, resuming as any step does, once
fewer steps run than ran beside it then, at most MEMORY_RETRIES times. Light steps (an
ahead-of-time compile) start beside a full set of jobs but hold a job's place while they
run (`run_side_by_side`): four paper-preset trainings beside the evaluation's compile ran
out of an 80 GB H100's memory twice in three runs, and a retry that waits for a free place
can delay the critical path by minutes.
"""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

POLL_S = 2.0
LOG_TAIL = 3000
OUT_OF_MEMORY = "RESOURCE_EXHAUSTED"  # XLA's error when an allocation does not fit
MEMORY_RETRIES = 2


def _child_env() -> dict[str, str]:
  env = dict(os.environ)
  if "XLA_PYTHON_CLIENT_MEM_FRACTION" not in env:
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
  env.setdefault("PYTHONUNBUFFERED", "1")
  return env


def _tail(path: str) -> str:
  return _written_since(path, 0)[-LOG_TAIL:]


def _written_since(path: str, offset: int) -> str:
  """What the log received from `offset` on (the latest call of its step)."""
  with open(path, errors="replace") as f:
    f.seek(offset)
    return f.read()


def run_side_by_side(names: Sequence[str], needs: Callable[[str], Sequence[str]],
        done: Callable[[str], bool], jobs: int, argv: Sequence[str], log_dir: str,
        light: Callable[[str], bool] = lambda name: False) -> int:
  """Runs every step of `names` not yet done; returns 0 when all finished, else 1.

  needs(name): the steps `name` waits for; done(name): whether it is complete on disk;
  argv: the pipeline script's own command line (script first), to which each child adds its step;
  light(name): a step that barely uses the accelerator (compiling ahead of time: host
  cores, and the kernels XLA runs to tune them): it starts whenever its needs are done,
  beside the `jobs` others; while it runs it holds a job's place, so the others wait until
  fewer than `jobs` run in all (measured: four paper-preset trainings beside the
  evaluation's ahead-of-time compile ran out of an 80 GB H100's memory twice in three runs).
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
  running: dict[str, tuple[subprocess.Popen, float, object, int]] = {}
  crowd: dict[str, int] = {}  # a step that ran out of memory: how many ran beside it
  retries: dict[str, int] = {}
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
      elif ((light(name) or len(running) < jobs)
            and len(running) < crowd.get(name, len(running) + 1)
            and all(d in finished for d in needs(name))):
        pending.remove(name)
        # a retry keeps the log of the call that ran out of memory
        log = open(os.path.join(log_dir, name.replace(":", "_") + ".log"),
                   "a" if name in crowd else "w")
        cmd = [sys.executable, *argv, f"--step={name}"]
        running[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                          env=_child_env()), time.perf_counter(), log,
                         log.tell())
        print(f"-- {name}: started ({len(running)} running, "
              f"{time.perf_counter() - t0:.0f} s in)", flush=True)
    time.sleep(POLL_S)
    beside = len(running) - 1  # steps that ran beside each one that ends now
    for name, (proc, start, log, offset) in list(running.items()):
      if proc.poll() is None:
        continue
      del running[name]
      log.close()
      seconds = time.perf_counter() - start
      if proc.returncode == 0 and (name == "report" or done(name)):
        finished.add(name)
        print(f"-- {name}: done in {seconds:.0f} s ({time.perf_counter() - t0:.0f} s in)",
              flush=True)
      elif (proc.returncode != 0 and beside > 0 and retries.get(name, 0) < MEMORY_RETRIES
            and OUT_OF_MEMORY in _written_since(log.name, offset)):
        retries[name] = retries.get(name, 0) + 1
        crowd[name] = beside
        pending.insert(0, name)
        print(f"-- {name}: out of accelerator memory after {seconds:.0f} s beside "
              f"{beside} other steps; it starts again once fewer run (retry "
              f"{retries[name]} of {MEMORY_RETRIES})", flush=True)
      else:
        failed.add(name)
        print(f"-- {name}: FAILED (exit {proc.returncode}) after {seconds:.0f} s; end of "
              f"{log.name}:\n{_tail(log.name)}", flush=True)
  print(f"-- all steps: {time.perf_counter() - t0:.0f} s wall, {jobs} at once"
        + (f"; failed or not started: {', '.join(sorted(failed))}" if failed else ""),
        flush=True)
  return 1 if failed else 0


def log_call(root: str, step: str, seconds: float, finished: bool) -> None:
  """Appends one call of `step` to ROOT/steps.jsonl."""
  import jax  # pylint: disable=import-outside-toplevel
  os.makedirs(root, exist_ok=True)
  dev = jax.devices()[0]
  end = time.time()  # start and end let the report count overlapping steps once
  with open(os.path.join(root, "steps.jsonl"), "a") as f:
    f.write(json.dumps({"step": step, "seconds": round(seconds, 1), "finished": finished,
                        "start": round(end - seconds, 1), "end": round(end, 1),
                        "device": f"{jax.device_count()} x {dev.device_kind}",
                        "date": datetime.date.today().isoformat()}) + "\n")


def wall_seconds(spans: list[tuple]) -> float:
  """The time in which at least one step ran: overlapping steps (--jobs) count once; a
  record without start and end (older logs) counts its own seconds."""
  total, reach = 0.0, -float("inf")
  for start, end, seconds in sorted(spans, key=lambda s: (s[0] is not None, s[0] or 0)):
    if start is None or end is None:
      total += seconds
    elif end > reach:
      total += end - max(start, reach)
      reach = end
  return total


def read_log(root: str) -> dict:
  """ROOT/steps.jsonl summed: {"steps": {name: {seconds, calls, device}}, "total_seconds",
  "wall_seconds"} (empty when nothing was logged)."""
  steps, spans = {}, []
  path = os.path.join(root, "steps.jsonl")
  if os.path.exists(path):
    with open(path) as f:
      for line in f:
        r = json.loads(line)
        s = steps.setdefault(r["step"], {"seconds": 0.0, "calls": 0, "device": r["device"]})
        s["seconds"] = round(s["seconds"] + r["seconds"], 1)
        s["calls"] += 1
        spans.append((r.get("start"), r.get("end"), r["seconds"]))
  return {"steps": steps,
          "total_seconds": round(sum(s["seconds"] for s in steps.values()), 1),
          "wall_seconds": round(wall_seconds(spans), 1)}


def steps_md(log: dict) -> list[str]:
  """The steps' wall-time table of a report."""
  lines = ["| step | calls | seconds | device |", "|---|--:|--:|---|"]
  lines += [f"| {k} | {s['calls']} | {s['seconds']:.0f} | {s['device']} |"
            for k, s in log["steps"].items()]
  return lines + ["", f"Total: {log['total_seconds'] / 60:.1f} min of steps, "
                  f"{log['wall_seconds'] / 60:.1f} min of wall time (steps run side by side "
                  "with --jobs count once)."]


def run_step(root: str, name: str, done: Callable[[], bool], action: Callable[[], None]
             ) -> bool:
  """Runs one call of a step and logs it; returns whether the step is now done. A call
  that raises is logged too (not finished: its time was spent), then the error goes on."""
  print(f"== {name}", flush=True)
  t0 = time.perf_counter()
  try:
    action()
  except BaseException:
    log_call(root, name, time.perf_counter() - t0, False)
    raise
  finished = name == "report" or done()
  log_call(root, name, time.perf_counter() - t0, finished)
  print(f"== {name}: {time.perf_counter() - t0:.0f} s"
        + ("" if finished else " (not finished: run again to go on)"), flush=True)
  return finished


def run_steps(pipe, step: str, jobs: int, argv: Sequence[str], list_only: bool = False
              ) -> int:
  """A pipeline script's main: `step` is "all" (every step left, in order), "next" (one
  call of the next step left) or a step's name; `jobs` > 1 with "all" runs steps side by
  side in child processes. `pipe` has .root, .steps() and .needs(name). Returns the exit
  status."""
  from absl import app  # pylint: disable=import-outside-toplevel
  steps = pipe.steps()
  names = [s[0] for s in steps]
  if list_only:
    for name, done, _ in steps:
      print(f"{'done' if done() else 'todo'}  {name}")
    return 0
  if step not in ("all", "next") and step not in names:
    raise app.UsageError(f"--step must be all, next or one of {', '.join(names)}")
  if jobs < 1:
    raise app.UsageError(f"--jobs must be at least 1, got {jobs}")
  if jobs > 1 and step == "all":
    import jax  # pylint: disable=import-outside-toplevel
    jax.config.update("jax_platforms", "cpu")  # the devices are the children's
    done = {name: d for name, d, _ in steps}
    return run_side_by_side(names, pipe.needs, lambda n: done[n](), jobs, argv,
                            os.path.join(pipe.root, "logs"),
                            light=getattr(pipe, "light", lambda name: False))
  for name, done, action in steps:
    if step not in ("all", "next", name) or (done() and step != name):
      continue
    while not run_step(pipe.root, name, done, action):
      if step == "next":
        return 0
    if step != "all":
      return 0
  return 0
