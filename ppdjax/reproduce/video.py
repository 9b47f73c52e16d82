"""The paper's real towers rebuilt in simulation (issue 19, paper Sec. 5.3 and 6).

  python -m ppdjax.reproduce video                                  # every step left
  python -m ppdjax.reproduce video --config=ppdjax/configs/video.py:tiny   # on a CPU
  python -m ppdjax.reproduce video --step=observe                   # one step

Steps: generate the pendulum dataset (`configs/video.py`: towers of pine, aluminium,
steel and copper struck by a copper ball on a pendulum); fine-tune the block towers' model
on it; observe the test towers (a fresh seed, 2, 3 and 4 blocks in 8 : 4 : 4): voxels, an
image and depth as the dataset's, and the trajectory only through a rendered video with
stickers, degraded and tracked (`ppdjax.video.observe`); decompose each (fit to the
voxels and depth, 512 density samples, with and without refinement: config.eval.refine
names the headline) from the tracked trajectory and, to price the tracker, from the true
one; report: density RMSE over all towers and the
2-block ones, "which block is heavier" on the 2-block towers (paper Fig. 9), into
experiments/results/video_towers.{md,json}, video_heavier.png and video.json; example:
docs/video.md's worked example, one tower filmed as the test towers are, as a user's
files in assets/video_example/ (`ppdjax.video.example`).
"""

from __future__ import annotations

import os
import sys

import jax
from absl import flags
from ml_collections import config_flags

jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("JAX_COMPILATION_CACHE_DIR", ".jax_cache"))

import numpy as np  # noqa: E402

from ppdjax.reproduce import blocks_common
from ppdjax.reproduce import steps as pipeline_steps
from ppdjax import primitives  # noqa: E402
from ppdjax.dataset import (camera, depth, generation, hollow, materials, render,  # noqa: E402
                            towers, voxels)
from ppdjax.sim import scene  # noqa: E402
from ppdjax.sim.simulate import simulate  # noqa: E402
from ppdjax.training import loop  # noqa: E402
from ppdjax.training.state import total_steps  # noqa: E402

config_flags.DEFINE_config_file("config", "ppdjax/configs/video.py", "Video preset.")
flags.DEFINE_string("root", "out/video", "Dataset, run and observations go here.")
flags.DEFINE_string("results", "experiments/results", "Where the report goes.")
flags.DEFINE_string("assets", "assets", "Where the worked example goes (video_example/).")
flags.DEFINE_integer("step_seconds", 540, "A training call stops after this long.")
flags.DEFINE_integer("workers", 0, "Processes filming and tracking (0: this one).")
flags.DEFINE_string("step", "all", "'all' (every step left), 'next', or a step name.")
flags.DEFINE_integer("jobs", 1, "Steps run at once (with --step=all).")
flags.DEFINE_bool("list", False, "Print the steps and their state, then exit.")
flags.DEFINE_string("report_name", "video_towers", "The report's name in --results (another "
                    "name for a validation set of towers: --config.test.seed=...).")
FLAGS = flags.FLAGS
EXTRA_STEPS = 12  # simulated beyond the recorded steps, so the last frame covers them
EXAMPLE_TRAVEL = 0.3  # m: the worked example's tower moves at least this far when struck
# the shipped example's clip: 640 x 480 at the renderer's 30 degrees, small to ship (the
# test clips' wider, larger view is for towers struck out of a narrower one)
EXAMPLE_FRAME = (480, 640)
EXAMPLE_TRIES = 100
VARIANTS = ("sample", "refine")  # +Sample, +Sample+Refine; config.eval.refine picks the headline


class Pipeline:
  """The steps, each a (name, done?, action); state lives only on disk."""

  def __init__(self, config, root: str):
    self.config, self.root = config, root
    self.data, self.workdir = os.path.join(root, "data"), os.path.join(root, "full")
    self.test_file = os.path.join(root, "test_towers.npz")
    self.eval_files = {v: os.path.join(root, f"decompositions_{v}.npz") for v in VARIANTS}
    self.example_dir = os.path.join(FLAGS.assets, "video_example")
    # the look-alike question: a model that reads no trajectory, beside (test.appearance)
    self.appearance = bool(config.test.get("appearance", False))
    self.appearance_dir = os.path.join(root, "appearance")
    if self.appearance:
      self.eval_files["appearance"] = os.path.join(root, "decompositions_appearance.npz")

  def appearance_config(self):
    return blocks_common.variant_config(self.config, "no_trajectory")  # Table 2's ablation

  def steps(self):
    return [("generate", lambda: os.path.exists(os.path.join(self.data, "manifest.json")),
             lambda: generation.generate(self.config, self.data)),
            ("train", lambda: loop.trained_steps(self.workdir) >= total_steps(
                self.config.train), self.train),
            *([("train_appearance", lambda: loop.trained_steps(self.appearance_dir)
                >= total_steps(self.config.train), self.train_appearance)]
              if self.appearance else []),
            ("observe", lambda: os.path.exists(self.test_file), self.observe),
            ("evaluate", lambda: all(map(os.path.exists, self.eval_files.values())),
             self.evaluate),
            ("report", lambda: False, self.report),
            ("example", lambda: os.path.exists(os.path.join(self.example_dir, "truth.json")),
             self.example)]

  def needs(self, name: str) -> tuple[str, ...]:
    return {"generate": (), "train": ("generate",), "train_appearance": ("generate",),
            "observe": (),
            "evaluate": ("train", "observe") + (("train_appearance",) if self.appearance
                                                else ()),
            "report": ("evaluate",), "example": ()}[name]

  def train(self) -> None:
    loop.train_and_evaluate(self.config, self.data, self.workdir,
                            time_limit_s=FLAGS.step_seconds)

  def train_appearance(self) -> None:
    loop.train_and_evaluate(self.appearance_config(), self.data, self.appearance_dir,
                            time_limit_s=FLAGS.step_seconds)

  def observe(self) -> None:
    """The test towers, observed: voxels, image and depth as the dataset's; the
    trajectory through a rendered, degraded video and the tracker."""
    from ppdjax.video.observe import observe_towers  # pylint: disable=import-outside-toplevel
    c, t = self.config, self.config.test
    rng = np.random.default_rng(t.seed)
    prims, ids = [], []
    for blocks, count in zip((2, 3, 4), t.counts):
      for _ in range(count):
        p, names = towers.sample_tower(rng, blocks, material_set="real")
        prims.append(p)
        ids.append([materials.ALL_MATERIAL_NAMES.index(n) for n in names]
                   + [-1] * (p.num_slots - blocks))
    prims, ids = primitives.stack(prims), np.asarray(ids, np.int32)
    scales = {}
    if c.data.get("hollow", 0.0) > 0:  # shells around cores, as the training data's
      prims, _ = hollow.hollow_blocks(rng, prims, ids, c.data.hollow)
      scales["inertia_scale"] = np.asarray(prims.inertia_scale)
    seeds = rng.integers(0, materials.TEXTURE_VARIANTS, ids.shape)
    looks = np.maximum(materials.look_ids(ids, c.data.get("look", "material")), 0)  # shown
    size = c.data.image_size
    with render.BatchRenderer(size, size, c.data.render_workers, depth=False) as renderer:
      images, _ = renderer.render(prims, looks, seeds)
    cam = camera.camera_dict(size, size)
    depths = np.asarray(depth.render_depths(prims, cam))
    vox = np.asarray(voxels.voxelize(prims))
    steps = c.data.steps
    truth = np.asarray(simulate(prims, generation.pushes_of(c.data), steps=steps + EXTRA_STEPS,
                                backend=c.data.backend), np.float32)[:, 0]
    rest = np.concatenate([np.asarray(jax.vmap(scene.rest_position)(prims)),
                           np.tile([1.0, 0.0, 0.0, 0.0], (len(ids), 1))], -1)
    tracked, errors = observe_towers(
        jax.tree.map(np.asarray, prims), looks, seeds, rest, truth, steps=steps,
        fps=t.fps, frame=tuple(t.frame), noise=t.noise, lighting=t.lighting, seed=t.seed,
        stickers=t.stickers, fovy=t.fovy, workers=FLAGS.workers)
    os.makedirs(self.root, exist_ok=True)
    np.savez_compressed(
        self.test_file, voxels=vox, image=images, depth=depths, true_trajectory=truth[:, :steps],
        tracked_trajectory=tracked, materials=ids, rest=rest, stickers=t.stickers,
        errors=np.asarray([e or "" for e in errors]), **scales,
        **{f: np.asarray(getattr(prims, f)) for f in primitives.FIELDS})

  def example(self) -> None:
    """docs/video.md's worked example: the first 2-block tower of two materials that the
    strike moves by EXAMPLE_TRAVEL or more, of a seed after the test towers', struck and
    filmed as they are (`video.example`), with the stickers docs/video.md advises (every
    face)."""
    from ppdjax.video.example import write_example  # pylint: disable=import-outside-toplevel
    c, t = self.config, self.config.test
    rng = np.random.default_rng(t.seed + 1)
    for _ in range(EXAMPLE_TRIES):  # two materials, a strike that moves it (heavy ones stay)
      p, names = towers.sample_tower(rng, 2, material_set="real")
      # MuJoCo C, not the training engine: a CPU makes it in seconds (the box-plane
      # engine compiles there for many minutes), and a user's real tower is no engine's
      truth = np.asarray(simulate(jax.tree.map(lambda a: np.asarray(a)[None], p),
                                  generation.pushes_of(c.data), steps=c.data.steps + EXTRA_STEPS,
                                  backend="mujoco"))[0, 0]
      if names[0] != names[1] and np.linalg.norm(truth[-1, :2]) > EXAMPLE_TRAVEL:
        break
    else:
      raise RuntimeError(f"none of {EXAMPLE_TRIES} towers of seed {t.seed + 1} moves "
                         f"{EXAMPLE_TRAVEL} m when struck: lower EXAMPLE_TRAVEL")
    ids = np.array([materials.ALL_MATERIAL_NAMES.index(n) for n in names]
                   + [0] * (p.num_slots - 2), np.int32)
    rest = np.concatenate([np.asarray(scene.rest_position(p)), [1.0, 0.0, 0.0, 0.0]])
    seeds = rng.integers(0, materials.TEXTURE_VARIANTS, ids.shape)
    write_example(self.example_dir, jax.tree.map(np.asarray, p), ids, seeds, rest, truth,
                  fps=t.fps, frame=EXAMPLE_FRAME, noise=t.noise, lighting=t.lighting,
                  stickers="all", seed=t.seed + 1,
                  material_names=list(materials.ALL_MATERIAL_NAMES))

  def evaluate(self) -> None:
    from ppdjax.reproduce import video_decompose  # pylint: disable=import-outside-toplevel
    files = {v: p for v, p in self.eval_files.items() if not os.path.exists(p)}
    if "appearance" in files:
      video_decompose.decompose_test(self.appearance_config(), self.appearance_dir,
                                     self.test_file, {"sample": files.pop("appearance")},
                                     network_only=True)
    if files:  # both, to show what refinement does (one refining pass where it can)
      video_decompose.decompose_test(self.config, self.workdir, self.test_file, files)

  def report(self) -> None:
    from ppdjax.reproduce import video_report as report  # pylint: disable=import-outside-toplevel
    args = [a for a in sys.argv[3:] if not a.startswith("--step=")]  # after the pipeline name
    result = report.write_report(self, FLAGS.results,
                                 "python -m ppdjax.reproduce video " + " ".join(args),
                                 FLAGS.report_name)
    if self.appearance:
      from ppdjax.reproduce import video_lookalike  # pylint: disable=import-outside-toplevel
      video_lookalike.extend_report(self, FLAGS.results, FLAGS.report_name, result)


def main(argv):
  del argv
  sys.exit(pipeline_steps.run_steps(Pipeline(FLAGS.config, FLAGS.root), FLAGS.step,
                                    FLAGS.jobs, sys.argv, list_only=FLAGS.list))

