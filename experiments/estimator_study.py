"""The density estimator on towers of a seed never trained on: trained, validated, tested.

Steps (each resumes or is skipped once done; `--step=all` runs them in order):

  data      a fresh dataset of the preset (seed --seed, one configuration per tower so that
            every object is a different tower), split 0 / 1/3 / 2/3 into train / val / test;
  train     the estimator of the preset (`python -m ppdjax.train_estimator`);
  validate  the shipped model (--model) + the estimator on the val split, no refinement: the
            τ of every +Sample row swept (free: candidates are simulated once);
  test      the test split with refinement: the reference without the estimator (the
            preset's τ), then the estimator at each of --weights, at the τ that gave the
            +Est+Sample row its best validation top-1 (validated at the first weight);
  report    experiments/results/estimator.{json,md} and estimator_training.png.

  python experiments/estimator_study.py --config=ppdjax/configs/paper.py --step=all
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
from absl import app, flags
from ml_collections import config_flags

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

from ppdjax.dataset import generation  # noqa: E402
from ppdjax.infer import evaluation, markdown  # noqa: E402
from ppdjax.training import estimator as est  # noqa: E402

STEPS = ("data", "train", "validate", "test", "report")
ROW = "PPD+Fit(depth)+Est+Sample"
_CONFIG = config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
_STEP = flags.DEFINE_enum("step", "all", STEPS + ("all",), "What to run.")
_ROOT = flags.DEFINE_string("root", "out/estimator_study", "Where the data and runs go.")
_MODEL = flags.DEFINE_string("model", "assets/blocks_model", "The PPD model (workdir or export).")
_SEED = flags.DEFINE_integer("seed", 20261123, "The fresh towers' seed (never trained on).")
_TOWERS = flags.DEFINE_integer("towers", 768, "Fresh towers (one configuration each).")
_OUT = flags.DEFINE_string("out", "experiments/results", "Where the report goes.")
_WEIGHTS = flags.DEFINE_list("weights", ["1.0", "0.3"], "Estimator weights tested (the first "
                             "is validated).")


def paths(root, weights=()):
  """Where each step writes: data, estimator, eval_val, eval_test_reference and one
  eval_test_w<weight> per tested weight."""
  out = {"data": os.path.join(root, "data"), "est": os.path.join(root, "estimator"),
         "val": os.path.join(root, "eval_val"),
         "test_reference": os.path.join(root, "eval_test_reference"),
         "steps": os.path.join(root, "steps.jsonl")}
  out.update({f"test_w{float(w)}": os.path.join(root, f"eval_test_w{float(w)}")
              for w in weights})
  return out


def _log(p, step, seconds):
  with open(p["steps"], "a") as f:
    f.write(json.dumps({"step": step, "seconds": round(seconds, 1),
                        "device": jax.devices()[0].device_kind}) + "\n")


def run_eval(config, p, name, split, *, refine, prior_weight, weight):
  """The shipped model's evaluation with depth-fitted boxes (and the estimator at `weight`
  unless it is None) into p[name], unless it is there."""
  out = p[name]
  if os.path.exists(os.path.join(out, "results.json")):
    with open(os.path.join(out, "results.json")) as f:
      return json.load(f)
  e = config.eval
  results = evaluation.evaluate(
      _MODEL.value, p["data"], split=split, samples=e.samples, refine=refine,
      refine_steps=e.refine_steps, batch_size=e.batch_size, with_baselines=False,
      prior_weight=prior_weight, fit=False, depth=True, refine_prior=e.refine_prior,
      estimator="" if weight is None else p["est"],
      estimator_weight=1.0 if weight is None else weight)
  markdown.write_results(results, out, "python " + " ".join(sys.argv))
  return results


def chosen_tau(val: dict) -> float:
  """The τ with the best validation top-1 of the +Est+Sample row (RMSE breaks ties)."""
  sweep = val["prior_sweeps"][ROW]
  return float(min(sweep, key=lambda t: (-sweep[t]["top1"], sweep[t]["rmse"])))


def main(_):
  config = _CONFIG.value
  weights = [float(w) for w in _WEIGHTS.value]
  p = paths(_ROOT.value, weights)
  os.makedirs(_ROOT.value, exist_ok=True)
  todo = STEPS if _STEP.value == "all" else (_STEP.value,)
  for step in todo:
    t0 = time.perf_counter()
    if step == "data":
      c = config.copy_and_resolve_references()
      c.seed, c.data.num_towers, c.data.configs_per_tower = _SEED.value, _TOWERS.value, 1
      c.data.towers_per_shard = min(c.data.towers_per_shard * 8, _TOWERS.value)
      c.data.split_fractions = (0.0, 1 / 3, 2 / 3)
      generation.generate(c, p["data"])
    elif step == "train":
      print(json.dumps(est.train_estimator(config, p["est"])))
    elif step == "validate":
      run_eval(config, p, "val", "val", refine=False, prior_weight=config.eval.prior_weight,
               weight=weights[0])
    elif step == "test":
      with open(os.path.join(p["val"], "results.json")) as f:
        tau = chosen_tau(json.load(f))
      print(f"tau chosen on validation: {tau}")
      run_eval(config, p, "test_reference", "test", refine=config.eval.refine,
               prior_weight=config.eval.prior_weight, weight=None)
      for w in weights:
        run_eval(config, p, f"test_w{w}", "test", refine=config.eval.refine, prior_weight=tau,
                 weight=w)
    else:
      import estimator_report  # beside this script
      estimator_report.write(p, weights, _OUT.value,
                             "python experiments/estimator_study.py --step=all "
                             f"--config=ppdjax/configs/{config.name}.py "
                             f"--weights={','.join(map(str, weights))}")
    _log(p, step, time.perf_counter() - t0)


if __name__ == "__main__":
  app.run(main)
