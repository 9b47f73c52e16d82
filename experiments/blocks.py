"""The whole block-tower experiment (paper Tables 2, 4, 5) in resumable steps of ≤ 10 minutes.

  python experiments/blocks.py                     # every step left, in order
  python experiments/blocks.py --step=next         # only the next step, then exit
  python experiments/blocks.py --list              # what is done and what is left

Steps: generate the `paper` dataset; train the full model and the no-trajectory,
no-image and no-voxels ablations; evaluate them on --max_objects test objects spread over
the split (the full model with +Sample, +Sample+Refine and the baselines; the ablations
plain); then `report`: experiments/results/blocks.{json,md} and PNGs, the full model
exported to assets/blocks_model and a decomposed example tower. Every step resumes:
generation by shard, training from its last checkpoint (a training step stops itself
after --step_seconds and the next call goes on); evaluations are skipped once written.
ROOT/steps.jsonl records each call's wall time and device.
"""

from __future__ import annotations

import datetime
import json
import os
import sys
import time

import jax
from absl import app, flags, logging
from ml_collections import config_flags

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

import blocks_common as common  # noqa: E402
import blocks_report  # noqa: E402
from ppdjax.dataset import generation  # noqa: E402
from ppdjax.infer import evaluation, tables  # noqa: E402
from ppdjax.training import loop  # noqa: E402

config_flags.DEFINE_config_file("config", "ppdjax/configs/paper.py", "Preset file.")
flags.DEFINE_string("root", "out/blocks_paper", "Dataset, runs and evaluations go here.")
flags.DEFINE_string("results", "experiments/results", "Where blocks.json/md and PNGs go.")
flags.DEFINE_string("assets", "assets", "Where the exported model and example tower go.")
flags.DEFINE_string("step", "all", "'all' (every step left), 'next', or a step name.")
flags.DEFINE_bool("list", False, "Print the steps and their state, then exit.")
flags.DEFINE_integer("max_objects", 128, "Evaluate on N test objects (0: all).")
flags.DEFINE_enum("subset", "spread", ["first", "spread"],
                  "The first N test objects, or N spread over the split (many towers).")
flags.DEFINE_integer("step_seconds", 540, "A training call stops after this long.")
FLAGS = flags.FLAGS
ORDER = ("full", "no_image", "no_trajectory", "no_voxels")


class Pipeline:
  """The steps, each with a test for done and an action; state lives only on disk."""

  def __init__(self, config, root: str):
    self.config, self.root = config, root
    self.data = os.path.join(root, "data")

  def workdir(self, variant: str) -> str:
    return os.path.join(self.root, variant)

  def eval_settings(self, variant: str) -> dict:
    e = self.config.eval
    if variant == "full":
      return {"samples": e.samples, "refine": e.refine, "with_baselines": True,
              "prior_weight": e.prior_weight}
    return {"samples": 1, "refine": False, "with_baselines": False, "prior_weight": 0.0}

  def eval_path(self, variant: str) -> str:
    return os.path.join(self.workdir(variant), "eval", "results.json")

  def steps(self) -> list[tuple[str, callable, callable]]:
    out = [("generate", lambda: os.path.exists(os.path.join(self.data, "manifest.json")),
            lambda: generation.generate(self.config, self.data))]
    t = self.config.train
    for v in ORDER:
      out.append((f"train:{v}", lambda v=v: loop.trained_steps(self.workdir(v))
                  >= total_steps(t), lambda v=v: self.train(v)))
    for v in ORDER:
      out.append((f"evaluate:{v}", lambda v=v: self.evaluated(v), lambda v=v: self.evaluate(v)))
    out.append(("report", lambda: False, self.report))
    return out

  def train(self, variant: str) -> None:
    loop.train_and_evaluate(common.variant_config(self.config, variant), self.data,
                             self.workdir(variant), time_limit_s=FLAGS.step_seconds)

  def evaluated(self, variant: str) -> bool:
    if not os.path.exists(self.eval_path(variant)):
      return False
    with open(self.eval_path(variant)) as f:
      r = json.load(f)
    s = self.eval_settings(variant)
    return ((r["samples"], r["refine"], r.get("max_objects", 0), r.get("prior_weight", 0.0),
             r.get("subset", "first")) ==
            (s["samples"], s["refine"], FLAGS.max_objects, s["prior_weight"], FLAGS.subset))

  def evaluate(self, variant: str) -> None:
    s, e = self.eval_settings(variant), self.config.eval
    results = evaluation.evaluate(self.workdir(variant), self.data,
                                  refine_steps=e.refine_steps, batch_size=e.batch_size,
                                  max_objects=FLAGS.max_objects, subset=FLAGS.subset, **s)
    results["max_objects"] = FLAGS.max_objects
    tables.write_results(
        results, os.path.dirname(self.eval_path(variant)),
        f"python -m ppdjax.evaluate --workdir={variant} --data=data --samples={s['samples']}"
        + (" --refine" if s["refine"] else "") + f" --prior_weight={s['prior_weight']}"
        + ("" if s["with_baselines"] else " --nobaselines")
        + (f" --max_objects={FLAGS.max_objects} --subset={FLAGS.subset}"
           if FLAGS.max_objects else ""))

  def report(self) -> None:
    blocks_report.write_all(self, FLAGS.results, FLAGS.assets,
                            "python experiments/blocks.py " + " ".join(sys.argv[1:]))

  def log(self, step: str, seconds: float, finished: bool) -> None:
    os.makedirs(self.root, exist_ok=True)
    dev = jax.devices()[0]
    with open(os.path.join(self.root, "steps.jsonl"), "a") as f:
      f.write(json.dumps({"step": step, "seconds": round(seconds, 1), "finished": finished,
                          "device": f"{jax.device_count()} x {dev.device_kind}",
                          "date": datetime.date.today().isoformat()}) + "\n")


def run_step(pipe: Pipeline, name: str, done, action) -> bool:
  """Runs one call of a step; returns whether the step is now done."""
  print(f"== {name}", flush=True)
  t0 = time.perf_counter()
  action()
  finished = name == "report" or done()
  pipe.log(name, time.perf_counter() - t0, finished)
  print(f"== {name}: {time.perf_counter() - t0:.0f} s"
        + ("" if finished else " (not finished: run again to go on)"), flush=True)
  return finished


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  pipe = Pipeline(FLAGS.config, FLAGS.root)
  steps = pipe.steps()
  names = [s[0] for s in steps]
  if FLAGS.list:
    for name, done, _ in steps:
      print(f"{'done' if done() else 'todo'}  {name}")
    return
  if FLAGS.step not in ("all", "next") and FLAGS.step not in names:
    raise app.UsageError(f"--step must be all, next or one of {', '.join(names)}")
  for name, done, action in steps:
    if FLAGS.step not in ("all", "next", name) or (done() and FLAGS.step != name):
      continue
    while not run_step(pipe, name, done, action):
      if FLAGS.step == "next":
        return
    if FLAGS.step != "all":
      return


if __name__ == "__main__":
  app.run(main)
