"""`python -m ppdjax.evaluate --workdir=DIR --data=DIR`: paper Tables 2, 4, 5 for one model.

Samples, refinement, batch size and τ default to the `eval` section of the preset the run
was trained with (WORKDIR/config.json); a flag overrides its value. Writes
OUT/results.json, results.md and confusion.png (OUT defaults to WORKDIR/eval).
"""

import os
import shutil
import sys

from absl import app, flags, logging

_WORKDIR = flags.DEFINE_string("workdir", None, "Training workdir (config.json and checkpoints).",
                               required=True)
_DATA = flags.DEFINE_string("data", None, "Dataset directory.", required=True)
_OUT = flags.DEFINE_string("out", None, "Output directory (default WORKDIR/eval).")
_SPLIT = flags.DEFINE_string("split", "test", "Split to evaluate.")
_SAMPLES = flags.DEFINE_integer("samples", None, "Density samples per object and baseline "
                                "(default: the preset's eval.samples).")
_REFINE = flags.DEFINE_bool("refine", None, "Refine the closest sample's densities through MJX "
                            "(default: eval.refine).")
_REFINE_STEPS = flags.DEFINE_integer("refine_steps", None, "Levenberg–Marquardt iterations "
                                     "(default: eval.refine_steps).")
_BATCH_SIZE = flags.DEFINE_integer("batch_size", None, "Objects per jitted call "
                                   "(default: eval.batch_size).")
_PRIOR_WEIGHT = flags.DEFINE_float("prior_weight", None, "+Sample selects by distance - "
                                   "prior_weight * log prior (metres per nat; default: "
                                   "eval.prior_weight; 0 is the paper's closest trajectory).")
_SELECTION_HORIZON = flags.DEFINE_integer(
    "selection_horizon", None, "+Sample's distance covers the first N steps (one of "
    "16, 32, 64, 128; 0: all, the paper's; default: eval.selection_horizon).")
_REFINE_HORIZON = flags.DEFINE_integer(
    "refine_horizon", None, "+Refine (and +Joint) start from the candidate closest over the "
    "first N steps (one of 16, 32, 64, 128; 0: all; default: eval.refine_horizon); they "
    "still fit the whole trajectory.")
_HORIZON_SWEEP = flags.DEFINE_bool(
    "horizon_sweep", False, "Also sweep τ at every horizon of --selection_horizon's choices "
    "(results.md's 'by τ and by the steps the distance covers'; about 0.4 s more per batch).")
_FIT = flags.DEFINE_bool("fit", None, "Also the +Fit rows: boxes fitted to the voxels "
                         "(default: eval.fit).")
_DEPTH = flags.DEFINE_bool("depth", None, "Also the +Fit(depth) rows: the fitted boxes refined "
                           "against the dataset's depth images (default: eval.depth).")
_REFINE_PRIOR = flags.DEFINE_float("refine_prior", None, "With --fit or --depth, +Refine is a "
                                   "MAP step "
                                   "under the network's density scores with this weight "
                                   "(default: eval.refine_prior; 0: least squares).")
_ESTIMATOR = flags.DEFINE_string("estimator", None, "A trained density estimator's folder "
                                 "(python -m ppdjax.train_estimator): adds the +Est rows on the "
                                 "most precise fitted boxes (default: eval.estimator).")
_ESTIMATOR_WEIGHT = flags.DEFINE_float("estimator_weight", None, "Weight of the estimator's "
                                       "log-probabilities beside the network's "
                                       "(default: eval.estimator_weight).")
_JOINT = flags.DEFINE_bool("joint", None, "With --fit or --depth, also +Joint: faces and "
                           "densities fitted together from +Refine's start (default: eval.joint).")
_TRUE_SHAPES = flags.DEFINE_bool("true_shapes", None, "Also the oracle rows on the true boxes "
                                 "(PPD+True boxes, +Sample, +Sample+Refine): what perfect "
                                 "boxes would give (default: eval.true_shapes).")
_REFINE_JACOBIAN = flags.DEFINE_enum(
    "refine_jacobian", None, ["forward", "differences", "central"],
    "How +Refine takes its Jacobian: forward mode, or forward or central differences (K + 1 "
    "or 2K + 1 rollouts in one call: 3x faster where the rollouts run as the GPU kernel, "
    "slightly less accurate) (default: eval.refine_jacobian).")
_TABLE4_OBJECTS = flags.DEFINE_integer(
    "table4_objects", None, "Table 4's sampling baselines on whole batches spread over at "
    "least this many objects, and Table 4 on those (0: every object; default: "
    "eval.table4_objects).")
_IMAGE_FIT = flags.DEFINE_bool(
    "image_fit", None, "With --fit, the +Fit rows' boxes are then refined against the edges "
    "of the dataset's images (the paper's inputs: voxels and image) (default: eval.image_fit).")
_FACE_SPREAD = flags.DEFINE_float(
    "face_spread", None, "With --fit, +Fit+Sample draws each candidate's faces too, uniform "
    "within this many voxels of the fitted ones (0.5: wherever the voxels allow them; 0: the "
    "fitted boxes only) (default: eval.face_spread).")
_MAX_OBJECTS = flags.DEFINE_integer("max_objects", 0, "Evaluate only N objects (0: all).")
_SUBSET = flags.DEFINE_enum("subset", "first", ["first", "spread"],
                            "With --max_objects: the first N objects, or N spread over the split.")
_BASELINES = flags.DEFINE_bool("baselines", True, "Also run Frequent, Nearest, Oracle and "
                               "Table 4's.")
_SEED = flags.DEFINE_integer("seed", 0, "Sampling seed.")
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
                                  "experiments/table5_errors.py).")


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  import jax
  if not jax.config.jax_compilation_cache_dir:  # the compiled programs are kept between runs
    jax.config.update("jax_compilation_cache_dir",
                      os.path.expanduser("~/.cache/ppdjax/jax_cache"))
  from ppdjax.dataset.storage import DatasetError
  from ppdjax.infer import evaluation, faces, markdown, partial, tables
  for flag in (_SELECTION_HORIZON, _REFINE_HORIZON):
    try:
      if flag.value is not None:
        tables.check_horizon("--" + flag.name, flag.value)
    except ValueError as e:
      sys.exit(f"error: {e}")
  from ppdjax.training import checkpoints
  try:
    model, config = checkpoints.load(_WORKDIR.value)
    settings = evaluation.eval_settings(config, samples=_SAMPLES.value, refine=_REFINE.value,
                                        refine_steps=_REFINE_STEPS.value,
                                        batch_size=_BATCH_SIZE.value,
                                        prior_weight=_PRIOR_WEIGHT.value, fit=_FIT.value,
                                        depth=_DEPTH.value, refine_prior=_REFINE_PRIOR.value,
                                        estimator=_ESTIMATOR.value,
                                        estimator_weight=_ESTIMATOR_WEIGHT.value,
                                        joint=_JOINT.value, true_shapes=_TRUE_SHAPES.value,
                                        selection_horizon=_SELECTION_HORIZON.value,
                                        refine_horizon=_REFINE_HORIZON.value,
                                        refine_jacobian=_REFINE_JACOBIAN.value,
                                        table4_objects=_TABLE4_OBJECTS.value,
                                        face_spread=_FACE_SPREAD.value,
                                        image_fit=_IMAGE_FIT.value)
    try:
      faces.check_spread(settings["face_spread"], settings["fit"])
    except ValueError as e:
      sys.exit(f"error: {e} (--face_spread, --fit)")
    if settings["image_fit"] and not settings["fit"]:
      sys.exit("error: --image_fit refines the +Fit rows' boxes: it needs --fit")
    out = _OUT.value or os.path.join(_WORKDIR.value, "eval")
    results = evaluation.evaluate((model, config), _DATA.value, split=_SPLIT.value,
                                  max_objects=_MAX_OBJECTS.value, subset=_SUBSET.value,
                                  with_baselines=_BASELINES.value, seed=_SEED.value,
                                  horizon_sweep=_HORIZON_SWEEP.value,
                                  partial_dir=("" if _COMPILE_ONLY.value
                                               else os.path.join(out, "partial")),
                                  max_seconds=_MAX_SECONDS.value,
                                  ahead=_COMPILE_ONLY.value, **settings)
  except (checkpoints.CheckpointError, DatasetError, partial.OtherEvaluation) as e:
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
  paths = markdown.write_results(results, out, command)
  if not _KEEP_RECORDS.value:
    shutil.rmtree(os.path.join(out, "partial"), ignore_errors=True)  # written: not needed
  else:  # one compressed file, small enough to keep with the results
    print(f"records kept in {partial.compact(os.path.join(out, 'partial'))}")
  rows = results["table2"]
  best = next(rows[r] for r in ("PPD+Fit(depth)+Est+Sample+Refine", "PPD+Fit+Est+Sample+Refine",
                                "PPD+Fit(depth)+Sample+Refine", "PPD+Fit+Sample+Refine",
                                "PPD+Fit(depth)+Sample", "PPD+Fit+Sample", "PPD+Sample+Refine",
                                "PPD+Sample", "PPD") if r in rows)
  print(f"F1 {results['f1']:.1f}; best row: top1 {best['top1']:.1f}, RMSE {best['rmse']:.2f}, "
        f"MAE {best['mae']:.1f} mm ({settings}) -> {paths[0]}, {paths[1]}")


if __name__ == "__main__":
  app.run(main)
