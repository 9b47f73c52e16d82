"""The whole block-tower experiment (paper Tables 2, 4, 5) in resumable steps of ≤ 10 minutes.

  python -m ppdjax.reproduce blocks                     # every step left, in order
  python -m ppdjax.reproduce blocks --step=next         # only the next step, then exit
  python -m ppdjax.reproduce blocks --list              # what is done and what is left
  python -m ppdjax.reproduce blocks --jobs=4            # independent steps side by side

Steps: generate the `paper` dataset; train the geometry stage (the voxel encoder and
generator on the stream of fresh towers, `train.stream_steps`), then the full model and
the no-trajectory and no-image ablations starting from it, and the no-voxels ablation
from scratch; evaluate the full model on --max_objects test objects spread over the split
(the whole split by default) with the preset's settings, which `decompose` then runs for
the exported model (the network's rows, +Sample, the +Fit rows on boxes fitted to the
voxels and the image, the paper's inputs, and the baselines; with
--config.eval.depth=True the fit reads the depth instead, as +Fit(depth); with
--config.eval.refine=True +Refine; with --joint +Sample+Joint; with --true_shapes the
true-box column), with --val_objects the +Sample studies on validation objects
(validate:full), and the ablations' networks on the whole split; `export`, once the full model is trained: it goes to assets/blocks_model, with an
example tower and the picture of its decomposition; then `report`:
experiments/results/blocks.{json,md} and PNGs.
Every step resumes:
generation by shard, training from its last checkpoint (a training step stops itself
after --step_seconds and the next call goes on); the test-split evaluations save each batch
as it is made and stop after --step_seconds too (the next call goes on); evaluations are
skipped once written.
ROOT/steps.jsonl records each call's wall time and device. With --jobs=N, up to N steps
whose inputs are ready run at once, each in its own process (ppdjax/reproduce/steps.py).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys

import jax
from absl import app, flags, logging
from ml_collections import config_flags

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

from ppdjax.reproduce import blocks_common as common
from ppdjax.reproduce import blocks_report
from ppdjax.reproduce import steps as pipeline_steps
from ppdjax.dataset import generation  # noqa: E402
from ppdjax.eval import evaluation, partial  # noqa: E402
from ppdjax.report import markdown
from ppdjax.nn.model import init_ppd  # noqa: E402
from ppdjax.training import checkpoints, loop  # noqa: E402
from ppdjax.training.state import total_steps  # noqa: E402

config_flags.DEFINE_config_file("config", "ppdjax/configs/paper.py", "Preset file.")
flags.DEFINE_string("root", "out/blocks_paper", "Dataset, runs and evaluations go here.")
flags.DEFINE_string("results", "experiments/results", "Where blocks.json/md and PNGs go.")
flags.DEFINE_string("assets", "assets", "Where the exported model and example tower go.")
flags.DEFINE_string("step", "all", "'all' (every step left), 'next', or a step name.")
flags.DEFINE_bool("list", False, "Print the steps and their state, then exit.")
flags.DEFINE_integer("max_objects", 0, "Evaluate the full model on N test objects (0: the "
                     "whole split, Tables 2 and 5's; the ablations always on all).")
flags.DEFINE_enum("subset", "spread", ["first", "spread"],
                  "The first N test objects, or N spread over the split (many towers).")
flags.DEFINE_integer("val_objects", 0, "Validation objects for a τ sweep of the full "
                     "model (0, the default: no validation step; τ = 0 is the preset's, "
                     "chosen on validation in experiments/results/mass_match_study).")
flags.DEFINE_bool("joint", False, "The full model's evaluation also runs +Joint (faces and "
                  "densities together; 4 s per batch of 64 on an H100, minutes to compile "
                  "on a CPU).")
flags.DEFINE_bool("true_shapes", False, "The full model's evaluation also runs the oracle "
                  "column: the same rows on the true boxes.")
flags.DEFINE_integer("step_seconds", 540, "A training or evaluation call stops after this "
                     "long (an evaluation after the batch that passes it).")
flags.DEFINE_integer("jobs", 1, "Steps run at once, each in its own process on the same "
                     "devices, as soon as the steps they need are done (with --step=all).")
flags.DEFINE_list("variants", ["full", "no_image", "no_trajectory", "no_voxels", "rgbd"],
                  "The model variants whose steps this call runs (the report needs full).")
flags.DEFINE_bool("exported", False, "The report only: the model and example tower in "
                  "--assets exist already (a report redone away from the run's machine, "
                  "from ROOT's results and logs; no checkpoints or dataset needed).")
FLAGS = flags.FLAGS
ORDER = ("full", "no_image", "no_trajectory", "no_voxels", "rgbd")
GEOMETRY = "geometry"  # the voxel-only geometry stage the voxel-using variants start from


class Pipeline:
  """The steps, each with a test for done and an action; state lives only on disk."""

  def __init__(self, config, root: str):
    self.config, self.root = config, root
    self.data = os.path.join(root, "data")

  def workdir(self, variant: str) -> str:
    return os.path.join(self.root, variant)

  def eval_settings(self, variant: str):
    """The typed eval section of a variant's test-split evaluation: the preset's (the
    full model: `decompose`'s settings and the tables') or the network alone."""
    if variant == "full":
      return evaluation.eval_settings(self.config, joint=FLAGS.joint,
                                      true_shapes=FLAGS.true_shapes)
    return evaluation.eval_settings(self.config, **common.NETWORK_ONLY)

  def evaluation_args(self, variant: str) -> dict:
    """`evaluation.evaluate`'s arguments for a variant's test-split evaluation (and for
    compiling it ahead: the same arguments compile the same programs)."""
    return {"settings": self.eval_settings(variant), "max_objects": self.max_objects(variant),
            "subset": FLAGS.subset}

  def max_objects(self, variant: str) -> int:
    """The full model's evaluation (sampling, baselines, fit, refinement) covers
    --max_objects test objects; the ablations' (the network alone) the whole split."""
    return FLAGS.max_objects if variant == "full" else 0

  def train_config(self, variant: str):
    """The geometry stage: the voxel pathway alone on the stream (train.stream_steps);
    the voxel-using variants start from it and keep the stream's loss beside theirs."""
    config = common.variant_config(self.config, "full" if variant == GEOMETRY else variant)
    t = config.train
    if variant == GEOMETRY:
      config.model.use_image = config.model.use_trajectory = False
      config.model.image_weights = ""
      t.geometry_steps = t.joint_steps = 0
    elif config.model.use_voxels and t.stream_steps:
      t.init_from, t.stream_steps = self.workdir(GEOMETRY), 0
    else:  # no voxels: nothing to take from the geometry stage
      t.stream_steps, t.stream_weight = 0, 0.0
    return config

  def eval_path(self, variant: str) -> str:
    return os.path.join(self.workdir(variant), "eval", "results.json")

  def steps(self) -> list[tuple[str, callable, callable]]:
    out = [("generate", lambda: os.path.exists(os.path.join(self.data, "manifest.json")),
            lambda: generation.generate(self.config, self.data))]
    unknown = set(FLAGS.variants) - set(ORDER)
    if unknown:
      raise app.UsageError(f"--variants: unknown {sorted(unknown)}; choose from {ORDER}")
    chosen = tuple(v for v in ORDER if v in FLAGS.variants)
    variants = ((GEOMETRY,) if self.config.train.stream_steps else ()) + chosen
    if "full" in chosen:  # its evaluation's programs, compiled while it trains
      out.append(("compile:full", self.compiled_ahead, self.compile_ahead))
    for v in variants:  # each model is evaluated as soon as it is trained
      out.append((f"train:{v}", lambda v=v: loop.trained_steps(self.workdir(v))
                  >= total_steps(self.train_config(v).train), lambda v=v: self.train(v)))
      if v != GEOMETRY:
        out.append((f"evaluate:{v}", lambda v=v: self.evaluated(v),
                    lambda v=v: self.evaluate(v)))
      if v == "full":  # the model and example shipped, beside the ablations
        out.append(("export", self.is_exported, self.export))
      if v == "full" and FLAGS.val_objects:
        out.append(("validate:full", self.validated, self.validate))
    if "full" in chosen:
      out.append(("report", lambda: False, self.report))
    return out

  def needs(self, name: str) -> tuple[str, ...]:
    """The steps that must be done before `name` starts (the data flow of steps())."""
    kind, _, variant = name.partition(":")
    if kind == "generate":
      return ()
    if kind == "train":
      if variant == GEOMETRY:  # the stream alone: it starts beside the generation
        return ()
      init = self.train_config(variant).train.get("init_from", "")
      return ("generate",) + ((f"train:{GEOMETRY}",) if init == self.workdir(GEOMETRY) else ())
    if kind in ("evaluate", "validate"):
      return (f"train:{variant}",)
    if kind == "export":
      return ("train:full",)
    if kind == "compile":  # the test split's first batch gives the shapes
      return ("generate",)
    return tuple(n for n, _, _ in self.steps() if n != "report")

  def light(self, name: str) -> bool:
    """Steps that barely use the accelerator: they start beside a full set of `--jobs`,
    and hold a job's place while they run (`pipeline_steps.run_side_by_side`)."""
    return name.startswith("compile:")

  def compile_record(self) -> str:
    return os.path.join(self.root, "compiled_ahead.json")

  def compile_stamp(self) -> dict:
    """What the compiled programs depend on: the evaluation's arguments, the model's
    configuration, JAX and the cache they went to."""
    args = self.evaluation_args("full")
    return {"evaluation": {**dataclasses.asdict(args.pop("settings")), **args},
            "model": self.train_config("full").model.to_dict(), "jax": jax.__version__,
            "cache": os.path.abspath(jax.config.jax_compilation_cache_dir)}

  def compiled_ahead(self) -> bool:
    """Done once the programs are in the cache for these settings, or once the full
    model's evaluation (which needs them no more) is."""
    if self.evaluated("full"):
      return True
    if not os.path.exists(self.compile_record()):
      return False
    with open(self.compile_record()) as f:
      return json.load(f).get("stamp") == json.loads(json.dumps(self.compile_stamp()))

  def compile_ahead(self) -> None:
    """The full model's evaluation compiled ahead of time into JAX's persistent cache
    (`evaluate(ahead=True)`), from a model of its configuration with fresh weights (the
    programs take the weights as arguments): evaluate:full then loads them instead of
    spending 90 s compiling while the accelerator waits."""
    config = self.train_config("full")
    model = init_ppd(config.model)
    try:
      r = evaluation.evaluate((model, config), self.data, ahead=True, progress=False,
                              **self.evaluation_args("full"))
      record = {"compile_seconds": r["compile_seconds"]}
      print(f"[full] evaluation compiled ahead in {r['compile_seconds']:.0f} s", flush=True)
    except Exception as error:  # pylint: disable=broad-except
      # only time is at stake: evaluate:full compiles for itself, and the report goes on
      record = {"error": f"{type(error).__name__}: {error}"}
      print(f"[full] compiling ahead failed ({record['error']}); evaluate:full will "
            "compile for itself", flush=True)
    common.write_json_atomically(self.compile_record(), {"stamp": self.compile_stamp(),
                                                         **record})

  def train(self, variant: str) -> None:
    loop.train_and_evaluate(self.train_config(variant), self.data, self.workdir(variant),
                             time_limit_s=FLAGS.step_seconds)

  def example_record(self) -> str:
    return os.path.join(self.workdir("full"), "example.json")

  def exported_example(self) -> dict:
    with open(self.example_record()) as f:
      return json.load(f)

  def export_stamp(self) -> dict:
    """What an export was made from and to: the full model's latest checkpoint (its step
    and time) and the folders written."""
    step = loop.trained_steps(self.workdir("full"))
    ckpt = os.path.join(self.workdir("full"), checkpoints.LATEST, str(step))
    return {"trained_steps": int(step),
            "checkpoint_mtime": os.path.getmtime(ckpt) if os.path.exists(ckpt) else None,
            "assets": os.path.abspath(FLAGS.assets), "results": os.path.abspath(FLAGS.results)}

  def is_exported(self) -> bool:
    """Whether the export step ran on the full model as trained now, into these folders,
    and its files are there."""
    files = [os.path.join(FLAGS.assets, "blocks_model", checkpoints.EXPORT),
             os.path.join(FLAGS.assets, "blocks_example.npz"),
             os.path.join(FLAGS.results, "blocks_decomposition.png"), self.example_record()]
    return (all(os.path.exists(f) for f in files)
            and self.exported_example().get("exported") == self.export_stamp())

  def export(self) -> None:
    blocks_report.export_example(self, FLAGS.results, FLAGS.assets)

  def evaluated(self, variant: str) -> bool:
    if not os.path.exists(self.eval_path(variant)):
      return False
    with open(self.eval_path(variant)) as f:
      r = json.load(f)
    return common.same_settings(r, self.eval_settings(variant),
                                max_objects=self.max_objects(variant), subset=FLAGS.subset)

  def val_path(self) -> str:
    return os.path.join(self.workdir("full"), "eval_val", "results.json")

  def val_settings(self):
    """The full model on validation objects, +Sample's studies (τ, horizons) where τ and
    the horizon are to be chosen: no baselines, no refinement."""
    return evaluation.eval_settings(self.config, refine=False, baselines=False,
                                    table4_objects=0, studies=True, horizon_sweep=True)

  def validated(self) -> bool:
    """Whether the validation sweep exists with this preset's settings and object count."""
    if not os.path.exists(self.val_path()):
      return False
    with open(self.val_path()) as f:
      r = json.load(f)
    return common.same_settings(r, self.val_settings(), max_objects=FLAGS.val_objects)

  def validate(self) -> None:
    """The full model on --val_objects validation objects, spread over the split."""
    s = self.val_settings()
    results = evaluation.evaluate(self.workdir("full"), self.data, s, split="val",
                                  max_objects=FLAGS.val_objects, subset="spread")
    results["max_objects"] = FLAGS.val_objects
    markdown.write_results(
        results, os.path.dirname(self.val_path()),
        common.eval_command("full", "data", s, split="val", max_objects=FLAGS.val_objects,
                            subset="spread"))

  def evaluate(self, variant: str) -> None:
    """One call of an evaluation step: batches are saved as they are made (eval_partial/),
    and the call stops after --step_seconds; the next call goes on from there."""
    s, n = self.eval_settings(variant), self.max_objects(variant)
    saved = os.path.join(self.workdir(variant), "eval_partial")
    run = lambda: evaluation.evaluate(self.workdir(variant), self.data, partial_dir=saved,
                                      max_seconds=FLAGS.step_seconds,
                                      **self.evaluation_args(variant))
    try:
      try:
        results = run()
      except partial.OtherEvaluation as stale:  # this step's own folder: start it again
        print(f"[{variant}] {stale}: starting again", flush=True)
        shutil.rmtree(saved)
        results = run()
    except partial.EvaluationPaused as paused:
      print(f"[{variant}] {paused}", flush=True)
      return
    results["max_objects"] = n
    markdown.write_results(
        results, os.path.dirname(self.eval_path(variant)),
        common.eval_command(variant, "data", s, max_objects=n or None,
                            subset=FLAGS.subset if n else None))
    if variant == "full":  # its per-object records, kept for studies away from the GPU
      partial.compact(saved)
    else:
      shutil.rmtree(saved, ignore_errors=True)

  def report(self) -> None:
    # the side-by-side runner adds --step= to its children's command lines
    args = [a for a in sys.argv[3:] if not a.startswith("--step=")]  # after the pipeline name
    blocks_report.write_all(self, FLAGS.results, FLAGS.assets,
                            "python -m ppdjax.reproduce blocks " + " ".join(args),
                            exported=FLAGS.exported)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  sys.exit(pipeline_steps.run_steps(Pipeline(FLAGS.config, FLAGS.root), FLAGS.step,
                                    FLAGS.jobs, sys.argv, list_only=FLAGS.list))

