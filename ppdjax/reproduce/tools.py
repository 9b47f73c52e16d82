"""The tools experiment (paper Sec. 5.2, Table 3) in resumable steps of <= --step_seconds.

  python -m ppdjax.reproduce tools --config=ppdjax/configs/tools.py        # every step left
  python -m ppdjax.reproduce tools --config=ppdjax/configs/tools.py:tiny   # the same on a CPU
  python -m ppdjax.reproduce tools --step=next                             # one call, then exit
  python -m ppdjax.reproduce tools --jobs=2        # independent steps side by side
  python -m ppdjax.reproduce tools --list                                  # done and left
  python -m ppdjax.reproduce tools --root=R2 --config.data.configs_per_tool=8 \
      --variants=full --pretrained=out/tools/pretrain  # a study: one model, no pretraining

Steps: generate the 2-block pretraining towers (`config.pretrain`) and the tools dataset;
for the realistic benchmark's labels, its floor (`ppdjax.eval.tool_floor`, CPU work);
pretrain the full model on the towers; fine-tune the full model and the no-image and
no-trajectory ablations on the tools from the pretrained weights (`config.finetune`);
evaluate each on the whole tools test split (the full model with the baselines, +Sample
and, with eval.fit, the +Fit rows); then `report`: experiments/results/tools.{json,md}
beside the paper's Table 3, a figure of decomposed test tools, and the full model exported
to assets/tools_model (under the paper's protocol, configs/tools_paper.py:
tools_paper.{json,md} and assets/tools_paper_model; `tools_report.names`). Generation resumes by shard, training from its last checkpoint
(a call stops itself after --step_seconds), evaluations by saved batch.
ROOT/steps.jsonl records each call's wall time and device (ppdjax/reproduce/steps.py);
with --jobs=N, up to N steps whose inputs are ready run at once, e.g. the tools are made
on the CPU while the model pretrains on the towers.

For a study of the tools data or the fine-tuning, --variants trains and evaluates only
some of the three models (the report, which needs all three, is then left out), and
--pretrained starts them from an existing pretraining workdir (another root's
ROOT/pretrain: the towers do not depend on the tools section) instead of making the
towers and pretraining again.
"""

from __future__ import annotations

import json
import os
import sys

import jax
from absl import app, flags
from ml_collections import config_flags

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

from ppdjax.reproduce import blocks_common as common
from ppdjax.reproduce import steps as pipeline_steps
from ppdjax.dataset import generation, tool_generation  # noqa: E402
from ppdjax.eval import evaluation, partial  # noqa: E402
from ppdjax.report import markdown
from ppdjax.training import loop  # noqa: E402
from ppdjax.training.state import total_steps  # noqa: E402

config_flags.DEFINE_config_file("config", "ppdjax/configs/tools.py", "Tools preset.")
flags.DEFINE_string("root", "", "Datasets, runs and evaluations go here (default: "
                    "out/<the preset's name>, e.g. out/tools, out/tools_paper).")
flags.DEFINE_string("results", "experiments/results", "Where the report's JSON, Markdown "
                    "and PNGs go (tools.* or, for the paper's protocol, tools_paper.*).")
flags.DEFINE_string("assets", "assets", "Where the exported tools model goes.")
flags.DEFINE_integer("step_seconds", 540, "A training or evaluation call stops after this long.")
flags.DEFINE_string("step", "all", "'all' (every step left), 'next', or a step name.")
flags.DEFINE_integer("jobs", 1, "Steps run at once, each in its own process (with "
                     "--step=all).")
flags.DEFINE_bool("list", False, "Print the steps and their state, then exit.")
VARIANTS = ("full", "no_image", "no_trajectory")
flags.DEFINE_list("variants", list(VARIANTS), "The fine-tuned models to train and evaluate; "
                  "the report only with all three.")
flags.DEFINE_string("pretrained", "", "Start the fine-tuning from this finished pretraining "
                    "workdir (e.g. another root's pretrain) instead of pretraining here.")
FLAGS = flags.FLAGS


class Pipeline:
  """The steps, each a (name, done?, action); state lives only on disk."""

  def __init__(self, config, root: str, variants=VARIANTS, pretrained: str = ""):
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown or not variants:
      raise app.UsageError(f"--variants must be some of {', '.join(VARIANTS)}, got "
                           f"{', '.join(variants) or 'none'}")
    self.config, self.root, self.pretrained = config, root, pretrained
    if pretrained and loop.trained_steps(pretrained) < total_steps(
        self.pretrain_config().train):
      raise app.UsageError(f"--pretrained={pretrained} holds no finished pretraining "
                           "(ROOT/pretrain of a tools run)")
    self.variants = tuple(v for v in VARIANTS if v in variants)
    self.data = os.path.join(root, "data")
    self.pretrain_data = os.path.join(root, "pretrain_data")

  def workdir(self, name: str) -> str:
    return os.path.join(self.root, name)

  def pretrain_config(self):
    """The towers' data section for pretraining (`config.pretrain`), same model."""
    c = self.config.copy_and_resolve_references()
    c.data.kind, c.data.backend = "towers", "mjx"
    c.data.num_towers = c.pretrain.num_towers
    c.data.num_blocks, c.data.rotate = c.pretrain.num_blocks, c.pretrain.rotate
    c.data.size_noise = c.pretrain.size_noise
    return c

  def train_config(self, variant: str):
    if variant == "pretrain":
      return self.pretrain_config()
    c = common.variant_config(self.config, variant)
    c.train.init_from = self.pretrained or self.workdir("pretrain")
    c.train.geometry_steps = c.finetune.geometry_steps
    c.train.joint_steps = c.finetune.joint_steps
    c.train.learning_rate = c.finetune.learning_rate
    c.train.eval_every = c.finetune.eval_every
    c.train.geometry_weight = c.finetune.get("geometry_weight", c.train.geometry_weight)
    c.train.warmup_steps = min(c.train.warmup_steps, c.finetune.geometry_steps)
    return c

  def eval_dir(self, variant: str) -> str:
    return os.path.join(self.workdir(variant), "eval")

  def steps(self):
    pretraining = () if self.pretrained else ("pretrain",)
    out = [("generate:pretrain", lambda: self._generated(self.pretrain_data),
            lambda: generation.generate(self.pretrain_config(), self.pretrain_data))
           ] if pretraining else []
    out.append(("generate:tools", lambda: self._generated(self.data),
                lambda: generation.generate(self.config, self.data)))
    for v in pretraining + self.variants:
      out.append((f"train:{v}", lambda v=v: loop.trained_steps(self.workdir(v))
                  >= total_steps(self.train_config(v).train), lambda v=v: self.train(v)))
      if v != "pretrain":
        out.append((f"evaluate:{v}", lambda v=v: os.path.exists(
            os.path.join(self.eval_dir(v), "results.json")), lambda v=v: self.evaluate(v)))
    if self.has_floor:  # the realistic benchmark's floor: CPU work beside the training
      out.append(("floor", lambda: os.path.exists(self.floor_file), self.floor))
    if self.variants == VARIANTS:  # the report needs every model
      out.append(("report", lambda: False, self.report))
    return out

  @property
  def has_floor(self) -> bool:
    """Whether the preset reads a floor (`ppdjax.eval.tool_floor`): the realistic labels."""
    return "floor" in self.config and tool_generation.materials_mode(
        self.config.data) == "plausible"

  @property
  def floor_file(self) -> str:
    return os.path.join(self.root, "floor", "floor.json")

  def floor(self) -> None:
    from ppdjax.eval import tool_floor  # pylint: disable=import-outside-toplevel
    result = tool_floor.compute(self.config, workers=int(self.config.data.render_workers))
    os.makedirs(os.path.dirname(self.floor_file), exist_ok=True)
    with open(self.floor_file + ".tmp", "w") as f:
      json.dump(result, f, indent=1)
    os.replace(self.floor_file + ".tmp", self.floor_file)
    print(f"floor: top-1 {result['top1']:.1f} %, RMSE {result['rmse']:.2f} over "
          f"{result['boxes']} boxes of {result['tools']} test tools -> {self.floor_file}",
          flush=True)

  def needs(self, name: str) -> tuple[str, ...]:
    """The steps that must be done before `name` starts (the data flow of steps())."""
    kind, _, variant = name.partition(":")
    if kind == "generate":
      return ()
    if kind == "train":
      return (("generate:pretrain",) if variant == "pretrain"
              else ("generate:tools",) + (() if self.pretrained else ("train:pretrain",)))
    if kind == "evaluate":
      return (f"train:{variant}",)
    if kind == "floor":  # after the tools are made: both keep the CPU's cores busy
      return ("generate:tools",)
    return tuple(n for n, _, _ in self.steps() if n != "report")

  def light(self, name: str) -> bool:
    """The floor is CPU work: it starts beside a full set of `--jobs` (the trainings)."""
    return name == "floor"

  @staticmethod
  def _generated(path: str) -> bool:
    return os.path.exists(os.path.join(path, "manifest.json"))

  def train(self, variant: str) -> None:
    data = self.pretrain_data if variant == "pretrain" else self.data
    loop.train_and_evaluate(self.train_config(variant), data, self.workdir(variant),
                            time_limit_s=FLAGS.step_seconds)

  def evaluate(self, variant: str) -> None:
    full = variant == "full"
    settings = (evaluation.eval_settings(self.config, refine=False) if full else
                evaluation.eval_settings(self.config, **common.NETWORK_ONLY))
    try:
      results = evaluation.evaluate(
          self.workdir(variant), self.data, settings, split="test",
          partial_dir=os.path.join(self.eval_dir(variant), "partial"),
          max_seconds=FLAGS.step_seconds)
    except partial.EvaluationPaused as paused:  # saved so far; the next call goes on
      print(f"[{variant}] {paused}", flush=True)
      return
    markdown.write_results(results, self.eval_dir(variant),
                           common.eval_command(variant, "data", settings, split="test"))
    if full:  # its per-object records in one compressed file, for studies away from the GPU
      partial.compact(os.path.join(self.eval_dir(variant), "partial"))

  def report(self) -> None:
    from ppdjax.reproduce import tools_report  # pylint: disable=import-outside-toplevel
    # the side-by-side runner adds --step= to its children's command lines
    args = [a for a in sys.argv[3:] if not a.startswith("--step=")]  # after the pipeline name
    tools_report.write_all(self, FLAGS.results, FLAGS.assets,
                           "python -m ppdjax.reproduce tools " + " ".join(args))


def main(argv):
  del argv
  root = FLAGS.root or os.path.join("out", FLAGS.config.name)
  pipe = Pipeline(FLAGS.config, root, FLAGS.variants, FLAGS.pretrained)
  sys.exit(pipeline_steps.run_steps(pipe, FLAGS.step, FLAGS.jobs, sys.argv,
                                    list_only=FLAGS.list))

