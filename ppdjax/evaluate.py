"""`python -m ppdjax.evaluate --workdir=DIR --data=DIR`: paper Tables 2, 4, 5 for one model.

Runs `decompose` with the model's own settings (the `eval` section it was saved with,
WORKDIR/config.json; `DecomposeConfig.from_eval`) and adds what the tables need;
`--config.eval.<key>=<value>` overrides a setting (keys: ppdjax/configs/schema.py,
`EvalConfig`). Writes OUT/results.json, results.md, confusion.png and the results'
provenance (OUT defaults to WORKDIR/eval).
"""

import os
import shutil
import sys

from absl import app, flags, logging

from ppdjax.configs import cli

_WORKDIR = flags.DEFINE_string("workdir", None, "Training workdir (config.json and checkpoints).",
                               required=True)
_DATA = flags.DEFINE_string("data", None, "Dataset directory.", required=True)
_OUT = flags.DEFINE_string("out", None, "Output directory (default WORKDIR/eval).")
_SPLIT = flags.DEFINE_string("split", "test", "Split to evaluate.")
_CONFIG = cli.define_model_overrides(("eval",))
_MAX_OBJECTS = flags.DEFINE_integer("max_objects", 0, "Evaluate only N objects (0: all).")
_SUBSET = flags.DEFINE_enum("subset", "first", ["first", "spread"],
                            "With --max_objects: the first N objects, or N spread over the split.")
_COMPILE_ONLY = flags.DEFINE_bool(
    "compile_only", False, "Compile the evaluation's programs ahead of time into JAX's "
    "persistent compilation cache (JAX_COMPILATION_CACHE_DIR, default ~/.cache/ppdjax/"
    "jax_cache) and exit: nothing runs on the accelerator, and an evaluation with the same "
    "flags of a model of the same configuration (any weights) then loads them.")
_MAX_SECONDS = flags.DEFINE_float("max_seconds", 0, "Stop after the batch that passes this "
                                  "many seconds (exit status 3); run the same command again "
                                  "to go on. 0: no limit. Either way, every batch's records "
                                  "are kept in OUT/partial until the results are written, so "
                                  "an interrupted evaluation resumes where it stopped.")
_KEEP_RECORDS = flags.DEFINE_bool("keep_records", False, "Keep OUT/partial, the per-object "
                                  "records, after the results are written, compacted into one "
                                  "compressed file (for studies of single objects, e.g. "
                                  "experiments/table5_errors/run.py).")


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  import jax
  if not jax.config.jax_compilation_cache_dir:  # the compiled programs are kept between runs
    jax.config.update("jax_compilation_cache_dir",
                      os.path.expanduser("~/.cache/ppdjax/jax_cache"))
  from ppdjax.configs.schema import ConfigError
  from ppdjax.dataset.storage import DatasetError
  from ppdjax.eval import evaluation, partial
  from ppdjax.report import markdown
  from ppdjax.training import checkpoints
  try:
    model, config = checkpoints.load(_WORKDIR.value)
    overrides = cli.model_overrides(("eval",))["eval"]
    out = _OUT.value or os.path.join(_WORKDIR.value, "eval")
    settings = evaluation.eval_settings(config, **overrides)
    results = evaluation.evaluate((model, config), _DATA.value, settings, split=_SPLIT.value,
                                  max_objects=_MAX_OBJECTS.value, subset=_SUBSET.value,
                                  partial_dir=("" if _COMPILE_ONLY.value
                                               else os.path.join(out, "partial")),
                                  max_seconds=_MAX_SECONDS.value, ahead=_COMPILE_ONLY.value)
  except (checkpoints.CheckpointError, DatasetError, partial.OtherEvaluation, ConfigError) as e:
    sys.exit(f"error: {e}")
  except partial.EvaluationPaused as e:
    print(f"paused: {e}")
    sys.exit(3)
  if _COMPILE_ONLY.value:
    print(f"compiled ahead in {results['compile_seconds']:.0f} s into "
          f"{jax.config.jax_compilation_cache_dir}")
    return
  results["workdir"] = _WORKDIR.value
  command = "python -m ppdjax.evaluate " + " ".join(sys.argv[1:])
  paths = markdown.write_results(results, out, command, config=config, weights=model)
  headline = results["headline"]
  if not _KEEP_RECORDS.value:
    shutil.rmtree(os.path.join(out, "partial"), ignore_errors=True)  # written: not needed
  else:  # one compressed file, small enough to keep with the results
    print(f"records kept in {partial.compact(os.path.join(out, 'partial'))}")
  row = results["table2"][headline]
  print(f"F1 {results['f1']:.1f}; {headline} (decompose's settings): top1 {row['top1']:.1f}, "
        f"RMSE {row['rmse']:.2f}, MAE {row['mae']:.1f} mm -> {paths[0]}, {paths[1]}")


if __name__ == "__main__":
  app.run(main)
