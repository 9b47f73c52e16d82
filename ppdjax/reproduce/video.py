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
experiments/results/video_towers.{md,json}, video_heavier.png and video.json.
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

from ppdjax.reproduce import steps as pipeline_steps
from ppdjax import primitives  # noqa: E402
from ppdjax.dataset import camera, depth, generation, materials, render, towers, voxels  # noqa: E402
from ppdjax.sim import scene  # noqa: E402
from ppdjax.sim.simulate import simulate  # noqa: E402
from ppdjax.training import loop  # noqa: E402
from ppdjax.training.state import total_steps  # noqa: E402

config_flags.DEFINE_config_file("config", "ppdjax/configs/video.py", "Video preset.")
flags.DEFINE_string("root", "out/video", "Dataset, run and observations go here.")
flags.DEFINE_string("results", "experiments/results", "Where the report goes.")
flags.DEFINE_integer("step_seconds", 540, "A training call stops after this long.")
flags.DEFINE_integer("workers", 0, "Processes filming and tracking (0: this one).")
flags.DEFINE_string("step", "all", "'all' (every step left), 'next', or a step name.")
flags.DEFINE_integer("jobs", 1, "Steps run at once (with --step=all).")
flags.DEFINE_bool("list", False, "Print the steps and their state, then exit.")
flags.DEFINE_string("report_name", "video_towers", "The report's name in --results (another "
                    "name for a validation set of towers: --config.test.seed=...).")
FLAGS = flags.FLAGS
EXTRA_STEPS = 12  # simulated beyond the recorded steps, so the last frame covers them
VARIANTS = ("sample", "refine")  # +Sample, +Sample+Refine; config.eval.refine picks the headline


class Pipeline:
  """The steps, each a (name, done?, action); state lives only on disk."""

  def __init__(self, config, root: str):
    self.config, self.root = config, root
    self.data, self.workdir = os.path.join(root, "data"), os.path.join(root, "full")
    self.test_file = os.path.join(root, "test_towers.npz")
    self.eval_files = {v: os.path.join(root, f"decompositions_{v}.npz") for v in VARIANTS}

  def steps(self):
    return [("generate", lambda: os.path.exists(os.path.join(self.data, "manifest.json")),
             lambda: generation.generate(self.config, self.data)),
            ("train", lambda: loop.trained_steps(self.workdir) >= total_steps(
                self.config.train), self.train),
            ("observe", lambda: os.path.exists(self.test_file), self.observe),
            ("evaluate", lambda: all(map(os.path.exists, self.eval_files.values())),
             self.evaluate),
            ("report", lambda: False, self.report)]

  def needs(self, name: str) -> tuple[str, ...]:
    return {"generate": (), "train": ("generate",), "observe": (),
            "evaluate": ("train", "observe"), "report": ("evaluate",)}[name]

  def train(self) -> None:
    loop.train_and_evaluate(self.config, self.data, self.workdir,
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
    seeds = rng.integers(0, materials.TEXTURE_VARIANTS, ids.shape)
    size = c.data.image_size
    with render.BatchRenderer(size, size, c.data.render_workers, depth=False) as renderer:
      images, _ = renderer.render(prims, np.maximum(ids, 0), seeds)
    cam = camera.camera_dict(size, size)
    depths = np.asarray(depth.render_depths(prims, cam))
    vox = np.asarray(voxels.voxelize(prims))
    steps = c.data.steps
    truth = np.asarray(simulate(prims, generation.pushes_of(c.data), steps=steps + EXTRA_STEPS,
                                backend=c.data.backend), np.float32)[:, 0]
    rest = np.concatenate([np.asarray(jax.vmap(scene.rest_position)(prims)),
                           np.tile([1.0, 0.0, 0.0, 0.0], (len(ids), 1))], -1)
    tracked, errors = observe_towers(
        jax.tree.map(np.asarray, prims), np.maximum(ids, 0), seeds, rest, truth, steps=steps,
        fps=t.fps, frame=tuple(t.frame), noise=t.noise, lighting=t.lighting, seed=t.seed,
        stickers=t.stickers, workers=FLAGS.workers)
    os.makedirs(self.root, exist_ok=True)
    np.savez_compressed(
        self.test_file, voxels=vox, image=images, depth=depths, true_trajectory=truth[:, :steps],
        tracked_trajectory=tracked, materials=ids, rest=rest, stickers=t.stickers,
        errors=np.asarray([e or "" for e in errors]),
        **{f: np.asarray(getattr(prims, f)) for f in primitives.FIELDS})

  def evaluate(self) -> None:
    from ppdjax.reproduce import video_report as report  # pylint: disable=import-outside-toplevel
    for variant, path in self.eval_files.items():  # both, to show what refinement does
      if not os.path.exists(path):
        report.decompose_test(self.config, self.workdir, self.test_file, path,
                              refine=variant == "refine")

  def report(self) -> None:
    from ppdjax.reproduce import video_report as report  # pylint: disable=import-outside-toplevel
    args = [a for a in sys.argv[3:] if not a.startswith("--step=")]  # after the pipeline name
    report.write_report(self, FLAGS.results,
                        "python -m ppdjax.reproduce video " + " ".join(args),
                        FLAGS.report_name)


def main(argv):
  del argv
  sys.exit(pipeline_steps.run_steps(Pipeline(FLAGS.config, FLAGS.root), FLAGS.step,
                                    FLAGS.jobs, sys.argv, list_only=FLAGS.list))

