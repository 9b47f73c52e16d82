"""`decompose` speed: one object (latency) and a batch (objects/s), MJX and the box-plane step
vs MuJoCo C.

  python experiments/benchmarks/bench_decompose.py --samples 512 --batch 64 --out FILE.json

Both engines run the same sampling in one process: the paper preset's network (random
weights: the cost does not depend on them) decodes the objects on the accelerator and
draws `samples` density assignments per object; then
  * MJX, and the box-plane step (`ppdjax.sim.box_plane`): everything above plus
    simulation under the four pushes, scoring and selection is the one jitted
    `ppdjax.make_decompose_fn` function;
  * C (peer): the same decode and draws (jitted), then all candidates simulated with
    `mujoco.batch` on every CPU core, scored with the same distance and selected.
Latency: median of --repeats warm calls for one object; throughput: objects / s of a
batch. `--depth` gives the observations depth images, which `decompose` then fits the
boxes to (and screens by default; the engine rows here are exhaustive, `screen_steps=0`).
`--screens 32:64,64:64` also times the GPU default engine with screened selection
(every candidate over the first 32 steps, the 64 closest over all 256; `make_decompose_fn(
screen_steps=, screen_keep=)`). Prints a markdown table.
"""

from __future__ import annotations

import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import nnx

import ppdjax
from ppdjax import metrics
from ppdjax.configs import paper
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset.camera import camera_dict
from ppdjax.dataset.depth import render_depths
from ppdjax.infer import sampling
from ppdjax.infer.decompose import model_settings
from ppdjax.nn.model import PPD
from ppdjax.sim import rollout_mjx
from ppdjax.sim.box_plane import BoxPlaneSettings

# The accelerator's engines, each at its package default settings.
# On a GPU the box-plane step runs as its Pallas kernel ("auto"); "(XLA)" is its reference.
ENGINES = {"MJX": rollout_mjx.MjxSettings(), "box-plane step": BoxPlaneSettings(),
           "box-plane step (XLA)": BoxPlaneSettings(kernel="reference")}

flags.DEFINE_integer("samples", 512, "Density samples per object.")
flags.DEFINE_integer("batch", 64, "Objects in the timed batch.")
flags.DEFINE_integer("repeats", 5, "Warm calls timed (median).")
flags.DEFINE_bool("refine", False, "Also time decompose(refine=True).")
flags.DEFINE_bool("skip_c", False, "The accelerator's engines only.")
flags.DEFINE_string("engines", ",".join(ENGINES), f"Comma-separated, of {list(ENGINES)}.")
flags.DEFINE_bool("skip_batch", False, "One object only.")
flags.DEFINE_bool("skip_one", False, "The batch only.")
flags.DEFINE_bool("skip_rollouts", False, "Not the rollouts alone (one more compilation per "
                  "engine).")
flags.DEFINE_bool("depth", False, "Observations with depth images: decompose fits the boxes to "
                  "them.")
flags.DEFINE_string("screens", "", "Comma-separated STEPS:KEEP screens to time on the box-plane "
                    "step.")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
FLAGS = flags.FLAGS


def observations(seed: int, count: int, image_size: int, depth: bool = False) -> dict:
  """Random towers' voxels, trajectories and (with `depth`) depth images from the
  datasets' camera; the image is noise (the network's weights are random too)."""
  prims = ppdjax.sample_towers(seed, count)
  rng = np.random.default_rng(seed)
  obs = {"voxels": ppdjax.voxelize(prims),
         "image": rng.integers(0, 255, (count, image_size, image_size, 3), np.uint8),
         "trajectories": np.asarray(ppdjax.simulate(prims))}
  if depth:
    obs["depth"] = np.asarray(render_depths(jax.tree.map(jnp.asarray, prims),
                                            camera_dict(image_size, image_size)))
  return obs


def timed(fn, repeats: int) -> tuple[object, float]:
  out = fn()  # warm-up (compiles)
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    out = fn()
    times.append(time.perf_counter() - t0)
  return out, float(np.median(times))


def c_peer(model, samples: int):
  """Decode + draws jitted on the accelerator; simulation and scoring in MuJoCo C."""
  graphdef, state = nnx.split(model)

  @jax.jit
  def propose(state, obs, key):
    prims, raw = nnx.merge(graphdef, state).decode(obs)
    logits = raw.density_logits[:, :prims.num_slots, :NUM_DENSITY_SLOTS]
    keys = jax.random.split(key, logits.shape[0])
    slots = jax.vmap(lambda lg, v, k: sampling.candidate_slots(lg, v, samples, k)[0])(
        logits, prims.valid, keys)
    return jax.vmap(sampling.with_slots)(prims, slots)

  def run(obs, key):
    cands = jax.device_get(propose(state, obs, key))  # (B, S, K)
    sim = ppdjax.simulate(cands, backend="mujoco")  # (B, S, P, T, 7), all cores
    dist = np.asarray(metrics.trajectory_distance(
        jnp.asarray(sim, jnp.float32), jnp.asarray(obs["trajectories"])[:, None]))
    return cands.density[np.arange(len(dist)), np.argmin(dist, -1)]
  return run


def main(argv):
  del argv
  config = paper.get_config()
  model = PPD(config.model, rngs=nnx.Rngs(0))
  size = config.data.image_size
  obs = observations(0, FLAGS.batch, size, FLAGS.depth)
  camera = camera_dict(size, size) if FLAGS.depth else None
  one = jax.tree.map(lambda x: x[:1], obs)
  key = jax.random.key(0)
  meta = {"device": jax.devices()[0].device_kind, "cpu_count": os.cpu_count(),
          "jax": jax.__version__, "python": platform.python_version(),
          "samples": FLAGS.samples, "batch": FLAGS.batch, "depth_fit": FLAGS.depth}
  rows = []

  def add(engine, what, n, seconds):
    rows.append({"engine": engine, "case": what, "objects": n, "seconds": seconds,
                 "objects_per_s": n / seconds})
    print(f"{engine:28s} {what:22s} {seconds * 1e3:9.1f} ms  {n / seconds:8.2f} objects/s",
          flush=True)

  runs = [(engine, settings, {"screen_steps": 0}) for engine, settings in ENGINES.items()
          if engine in FLAGS.engines.split(",")]
  for screen in filter(None, FLAGS.screens.split(",")):
    steps, keep = (int(x) for x in screen.split(":"))
    runs.append((f"box-plane step, screen {steps} steps -> {keep}", ENGINES["box-plane step"],
                 {"screen_steps": steps, "screen_keep": keep}))
  for engine, settings, screen in runs:
    shipped = model_settings((model, config)).replace(**{
        "select.samples": FLAGS.samples, **{"select." + k: v for k, v in screen.items()}})
    decompose = ppdjax.make_decompose_fn((model, config), shipped, engine=settings,
                                         camera=camera)
    block = lambda out: jax.block_until_ready(out.primitives.density)
    if not FLAGS.skip_one:
      t0 = time.perf_counter()
      block(decompose(one, key))
      meta[f"compile_one_s {engine}"] = time.perf_counter() - t0
      _, s = timed(lambda: block(decompose(one, key)), FLAGS.repeats)
      add(f"{engine} (jitted decompose)", "1 object", 1, s)
    if not FLAGS.skip_batch:
      _, s = timed(lambda: block(decompose(obs, key)), max(1, FLAGS.repeats // 2))
      add(f"{engine} (jitted decompose)", f"batch of {FLAGS.batch}", FLAGS.batch, s)
    if screen["screen_steps"] or FLAGS.skip_rollouts:
      continue  # the rest is the engine's, timed above
    physics_only = jax.jit(lambda c, s=settings: rollout_mjx.simulate(
        c, ppdjax.default_pushes(), settings=s))
    cands = jax.tree.map(lambda x: jnp.broadcast_to(x[0], (FLAGS.samples,) + x.shape[1:]),
                         jax.tree.map(jnp.asarray, ppdjax.sample_towers(1, 1)))
    _, s = timed(lambda: jax.block_until_ready(physics_only(cands)), FLAGS.repeats)
    add(f"{engine} rollouts alone", f"{FLAGS.samples} candidates", 1, s)
    if FLAGS.refine:
      refined = ppdjax.make_decompose_fn(
          (model, config), shipped.replace(**{"refine.enabled": True}), engine=settings,
          camera=camera)
      _, s = timed(lambda: block(refined(one, key)), FLAGS.repeats)
      add(f"{engine} decompose + refine", "1 object", 1, s)
  if not FLAGS.skip_c:
    peer = c_peer(model, FLAGS.samples)
    if not FLAGS.skip_one:
      _, s = timed(lambda: peer(one, key), max(1, FLAGS.repeats // 2))
      add(f"MuJoCo C, {os.cpu_count()} threads", "1 object", 1, s)
    if not FLAGS.skip_batch:
      _, s = timed(lambda: peer(obs, key), 1)
      add(f"MuJoCo C, {os.cpu_count()} threads", f"batch of {FLAGS.batch}", FLAGS.batch, s)
  c = {r["case"]: r["seconds"] for r in rows if r["engine"].startswith("MuJoCo C")}
  print("\n| engine | case | ms | objects/s | × C |\n|---|---|--:|--:|--:|")
  for r in rows:
    ratio = c.get(r["case"], float("nan")) / r["seconds"]
    print(f"| {r['engine']} | {r['case']} | {r['seconds'] * 1e3:.1f} | "
          f"{r['objects_per_s']:.2f} | {ratio:.2f} |")
  if FLAGS.out:
    with open(FLAGS.out, "w") as f:
      json.dump({"meta": meta, "rows": rows}, f, indent=1)


if __name__ == "__main__":
  app.run(main)
