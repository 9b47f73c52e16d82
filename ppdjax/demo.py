"""`python -m ppdjax.demo --config=ppdjax/configs/tiny.py --out=out/demo`: the quick-start job.

1. The shipped model (assets/blocks_model) decomposes the shipped example tower:
   OUT/example.png (input, recovered boxes coloured by density, truth) and OUT/example.md
   (each box's density and overlap beside the truth).
2. One random tower under the paper's four pushes, in MJX and MuJoCo C:
   OUT/trajectories.png, OUT/summary.md.
3. A smoke run of the training pipeline on the preset (tiny: 16 towers, 60 steps):
   OUT/smoke/blocks (dataset and card), OUT/smoke/train (checkpoints, learning curve),
   OUT/smoke/eval (Tables 2, 4, 5) and OUT/smoke/decomposition.png. It shows the pipeline
   runs end to end; a model this small and this briefly trained decomposes nothing well.
Rerun it and the dataset and training resume where they stopped.
"""

import concurrent.futures
import os
import time

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
_OUT = flags.DEFINE_string("out", "out/demo", "Output directory.")
_MODEL = flags.DEFINE_string("model", "assets/blocks_model", "The trained model to show.")
_EXAMPLE = flags.DEFINE_string("example", "assets/blocks_example.npz", "The tower it decomposes.")


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  import jax
  if not jax.config.jax_compilation_cache_dir:  # as `ppdjax.evaluate`: a rerun compiles
    # little, and the smoke run's last decompose can find the evaluation's program
    jax.config.update("jax_compilation_cache_dir",
                      os.path.expanduser("~/.cache/ppdjax/jax_cache"))
  from ppdjax import showcase
  from ppdjax.infer import example
  config, out = _CONFIG.value, _OUT.value
  demo = config.demo
  fit = "the voxels and the image" if demo.example_image_fit else "the voxels"
  clock = time.perf_counter()
  took = lambda: f"({time.perf_counter() - clock:.0f} s)"
  print(f"[1/3] the shipped model decomposes the example tower (boxes fitted to {fit}, "
        f"{demo.example_samples} density samples simulated; the first call compiles; step "
        "2's rollouts compile beside it)...", flush=True)
  # Steps 1 and 2 are mostly single-threaded compilation on a CPU: side by side they took
  # 66 s instead of 77 on 2 cores. Step 3 beside them was slower (its data generation and
  # training use both cores), so it waits.
  with concurrent.futures.ThreadPoolExecutor(1) as pool:
    rollouts = pool.submit(showcase.physics_rollouts, config)
    r = showcase.shipped_example(_MODEL.value, _EXAMPLE.value, out, demo.example_samples,
                                 image_fit=demo.example_image_fit)
    print(f"  {r['shape_matched']}/{len(r['true_densities'])} boxes found (IoU > 0.5); "
          f"densities {[round(d) for d in r['densities']]} kg/m³, true "
          f"{[round(d) for d in r['true_densities']]}. {example.heaviest_line(r)} -> "
          f"{out}/example.png, example.md {took()}", flush=True)
    clock = time.perf_counter()
    reference = f" and {demo.reference_backend}" if demo.reference_backend else ""
    print(f"[2/3] physics: one random tower of {demo.num_blocks} blocks under the paper's four "
          f"pushes, {demo.steps} steps in {demo.backend}{reference}...", flush=True)
    summary = showcase.physics_tour(config, out, rollouts.result())
  print(f"  speeds after the pushes {summary['speed_after_push_m_s']} m/s -> "
        f"{out}/trajectories.png, summary.md {took()}", flush=True)
  clock = time.perf_counter()
  print(f"[3/3] smoke run of the training pipeline ({config.name} preset: it checks that "
        "generate -> train -> evaluate runs, not how well the method works)...", flush=True)
  showcase.smoke_run(config, os.path.join(out, "smoke"))
  print(f"  {took()}", flush=True)
  print(f"done: {out}/example.md, {out}/summary.md, {out}/smoke/eval/results.md")


if __name__ == "__main__":
  app.run(main)
