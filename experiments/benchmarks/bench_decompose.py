"""The front door's speed: `make_decompose_fn` as users call it, with the shipped model's
settings, beside MuJoCo C on every core simulating the same rollouts, in one process.

  python experiments/benchmarks/bench_decompose.py --model=assets/blocks_model --batch=64 \
      --out=FILE.json [--front_door=experiments/results/bench_front_door.json]

Settings timed: the model's own (`make_decompose_fn(model)`, no config: for the blocks
model the paper's inputs, image fit and 32-step selection) and `DecomposeConfig.best()`
(depth fit, screen, refinement by differences). Objects: the shipped example tower (one
object) and `--batch` fresh towers of a seed never trained on, generated as the model's
dataset (rendered images and depth). Each call is the public one, warm (median of
`--repeats`), except "first call", which compiles (run in a fresh process, without the
persistent compilation cache). On a CPU the call simulates with MuJoCo C (the default
`simulator="auto"`); on a GPU with the JAX engine of the model's data.

Peer: MuJoCo C (`mujoco.batch`, `os.cpu_count()` threads) simulating what the call
simulates: as many rollouts of each length, from the call's own candidates (its fitted
boxes with the density slots it draws: `sampling.candidate_slots` from `object_keys`).
`--front_door` merges the figures into that results file (keys of issue 59).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import generation
from ppdjax.infer import example, sampling
from ppdjax.infer.config import DecomposeConfig
from ppdjax.infer.decompose import model_settings, object_keys
from ppdjax.report.provenance import write_provenance
from ppdjax.sim import rollout_mujoco
from ppdjax.training import checkpoints

flags.DEFINE_string("model", "assets/blocks_model", "The model (exported or a workdir).")
flags.DEFINE_string("example", "assets/blocks_example.npz", "The one object.")
flags.DEFINE_integer("batch", 64, "Objects in the timed batch (0: none).")
flags.DEFINE_integer("repeats", 5, "Warm calls timed (median).")
flags.DEFINE_integer("seed", 90_101, "Seed of the fresh towers (never used for training).")
flags.DEFINE_list("settings", ["model", "best"], "Which settings: model, best.")
flags.DEFINE_bool("first_call", True, "Also time a first call (compilation) in a fresh "
                  "process without the persistent cache.")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
flags.DEFINE_string("front_door", "", "Merge the figures into this results file.")
FLAGS = flags.FLAGS


def fresh_objects(trained, count: int, seed: int, folder: str) -> tuple[dict, dict]:
  """`count` observations (with depth) of fresh towers made as the model's dataset, and
  their camera."""
  per = trained[1].data.configs_per_tower
  test = generation.generate_fresh(trained[1], folder, -(-count // per), seed)
  return test.take(np.arange(count), keys=OBS_KEYS + ("depth",)), test.camera


def timed(fn, repeats: int) -> float:
  fn()  # warm
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    fn()
    times.append(time.perf_counter() - t0)
  return float(np.median(times))


def simulated_rollouts(config: DecomposeConfig, steps: int, num_boxes: int) -> list:
  """[(candidates, steps)] per object: the rollouts (under every push) the call simulates."""
  s = config.select
  out = []
  if 0 < s.screen_steps < steps and s.screen_keep < s.samples:
    out += [(s.samples, s.screen_steps), (s.screen_keep, steps)]
  elif 0 < s.horizon < steps and not config.refine.enabled:
    out += [(s.samples, s.horizon), (1, steps)]  # the winner alone over every step
  else:
    out += [(s.samples, steps)]
  if config.refine.enabled:  # LM: steps + 1 passes of K + 1 rollouts (differences), last one
    per = num_boxes + 1 if config.refine.jacobian == "differences" else 2 * num_boxes + 1
    out += [((config.refine.steps + 1) * per + 1, steps)]
  return out


def c_peer(result, obs, config: DecomposeConfig, key, pushes, full: bool = False):
  """MuJoCo C on every core simulating the call's rollouts from its candidates; with
  `full`, every candidate over the whole trajectory (what the call simulated before the
  selection horizon stopped early: issue 59's peer)."""
  prims = jax.device_get(result.primitives)
  logits = jnp.asarray(result.density_logits)
  batch = prims.density.shape[0]
  keys = object_keys(key, batch)
  slots = jax.jit(jax.vmap(lambda lg, v, k: sampling.candidate_slots(
      lg, v, config.select.samples, k)[0]))(logits, jnp.asarray(prims.valid), keys)
  cands = jax.device_get(jax.vmap(sampling.with_slots)(jax.tree.map(jnp.asarray, prims),
                                                       slots))  # (B, S, K)
  steps = np.shape(obs["trajectories"])[-2]
  plan = ([(config.select.samples, steps)] if full else
          simulated_rollouts(config, steps, prims.valid.shape[-1]))

  def run():
    for count, length in plan:
      reps = -(-count // config.select.samples)
      part = jax.tree.map(lambda x: np.concatenate([x] * reps, 1)[:, :count], cands)
      rollout_mujoco.simulate(part, pushes, steps=length)
  return run, plan


def first_call_seconds(model: str, example_path: str) -> float:
  """The model's settings on the example, first call (compiles) in a fresh process."""
  code = ("import time, jax, ppdjax\nfrom ppdjax.infer import example\n"
          f"obs, _ = example.load_example({example_path!r})\n"
          f"d = ppdjax.make_decompose_fn({model!r})\n"
          "t = time.perf_counter(); jax.block_until_ready(d(obs, jax.random.key(0)))\n"
          "print(time.perf_counter() - t)\n")
  env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       check=True)
  return float(out.stdout.strip().splitlines()[-1])


def main(argv):
  del argv
  platform_name = jax.default_backend()
  device = jax.devices()[0].device_kind
  threads = os.cpu_count()
  print(f"{platform_name}: {device}; MuJoCo C on {threads} threads", flush=True)
  trained = checkpoints.load(FLAGS.model)
  pushes = generation.pushes_of(trained[1].data)
  one_obs, _ = example.load_example(FLAGS.example)
  camera = example.load_camera(FLAGS.example)
  many = None
  if FLAGS.batch:
    with tempfile.TemporaryDirectory() as folder:
      many, data_camera = fresh_objects(trained, FLAGS.batch, FLAGS.seed, folder)
  rows = {}
  key = jax.random.key(0)
  meta = {"device": device, "platform": platform_name, "cpu_count": threads,
          "jax": jax.__version__, "python": platform.python_version(),
          "date": datetime.date.today().isoformat(),
          "command": "python " + " ".join(shlex.quote(a) for a in sys.argv)}

  def save():  # after every row: a run cut short keeps what it measured
    if FLAGS.out:
      with open(FLAGS.out, "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)

  def add(name, seconds, objects, peer, plan):
    rows[name] = {"seconds": seconds, "objects": objects, "objects_per_s": objects / seconds,
                  "c_peer_seconds": peer, "ratio_to_c": seconds / peer if peer else None,
                  "rollouts_per_object": [list(p) for p in plan]}
    print(f"{name:34s} {seconds * 1e3:10.1f} ms  {objects / seconds:8.2f} objects/s  "
          f"C peer {peer * 1e3 if peer else float('nan'):10.1f} ms  "
          f"(x{seconds / peer if peer else float('nan'):.2f})", flush=True)
    save()

  for which in FLAGS.settings:
    config = model_settings(trained) if which == "model" else DecomposeConfig.best()
    if config.fit.depth and "depth" not in one_obs:
      print(f"{which}: the example has no depth; skipped", flush=True)
      continue
    decompose = ppdjax.make_decompose_fn(trained, config, camera=camera if config.fit.with_
                                         else None)
    print(f"{which}: {config} on {decompose.settings}", flush=True)
    block = lambda out: jax.block_until_ready(out)
    result = block(decompose(one_obs, key))
    seconds = timed(lambda: block(decompose(one_obs, key)), FLAGS.repeats)
    batched, obs_one = (jax.tree.map(lambda x: np.asarray(x)[None], t) for t in (result, one_obs))
    run, plan = c_peer(batched, obs_one, config, key, pushes)
    add(f"{which}: one object", seconds, 1, timed(run, FLAGS.repeats), plan)
    run_full, _ = c_peer(batched, obs_one, config, key, pushes, full=True)
    peer_full = timed(run_full, FLAGS.repeats)
    rows[f"{which}: one object"].update(c_peer_full_seconds=peer_full,
                                        ratio_to_c_full=seconds / peer_full)
    print(f"{'':34s} C, every candidate over every step {peer_full * 1e3:10.1f} ms  "
          f"(x{seconds / peer_full:.2f})", flush=True)
    save()
    if many is not None:
      decompose_many = ppdjax.make_decompose_fn(
          trained, config, camera=data_camera if config.fit.with_ else None)
      obs = {k: many[k] for k in OBS_KEYS + (("depth",) if config.fit.depth else ())}
      result = block(decompose_many(obs, key))
      seconds = timed(lambda: block(decompose_many(obs, key)), max(1, FLAGS.repeats // 2))
      run, plan = c_peer(result, obs, config, key, pushes)
      add(f"{which}: batch of {FLAGS.batch}", seconds, FLAGS.batch, timed(run, 1), plan)
  if FLAGS.first_call and "model" in FLAGS.settings:
    seconds = first_call_seconds(FLAGS.model, FLAGS.example)
    rows["model: first call"] = {"seconds": seconds, "objects": 1}
    print(f"model: first call (compiles)      {seconds:10.1f} s", flush=True)
  save()
  if FLAGS.out:
    write_provenance(FLAGS.out, command=sys.argv, weights=FLAGS.model, headlines={
        f"{name} (s)": f"rows/{name}/seconds" for name in rows})
  if FLAGS.front_door:
    merge_front_door(FLAGS.front_door, rows, meta)


def merge_front_door(path: str, rows: dict, meta: dict) -> None:
  """The results file's rows for this platform (issue 59's keys)."""
  machine = f"{meta['device']}, {meta['cpu_count']} CPU cores"
  entry = lambda value, unit: {"value": round(value, 4), "unit": unit, "machine": machine,
                               "date": meta["date"], "command": meta["command"]}
  out = json.load(open(path)) if os.path.exists(path) else {}
  batch = next((k for k in rows if k.startswith("model: batch")), None)
  best = next((k for k in rows if k.startswith("best: batch")), None)
  if meta["platform"] == "cpu":
    if "model: one object" in rows:
      r = rows["model: one object"]
      out["cpu_one_object_s"] = entry(r["seconds"], "s")
      out["c_peer_cpu_one_object_s"] = entry(r["c_peer_seconds"], "s")
      if "c_peer_full_seconds" in r:
        out["c_peer_full_cpu_one_object_s"] = entry(r["c_peer_full_seconds"], "s")
    if "model: first call" in rows:
      out["cpu_first_call_s"] = entry(rows["model: first call"]["seconds"], "s")
  else:
    if "model: one object" in rows:
      r = rows["model: one object"]
      out["gpu_one_object_ms"] = entry(r["seconds"] * 1e3, "ms")
      out["c_peer_gpu_one_object_ms"] = entry(r["c_peer_seconds"] * 1e3, "ms")
      if "c_peer_full_seconds" in r:
        out["c_peer_full_gpu_one_object_ms"] = entry(r["c_peer_full_seconds"] * 1e3, "ms")
    for key, name in ((batch, "gpu_batch64_paper_objects_per_s"),
                      (best, "gpu_batch64_depth_refine_objects_per_s")):
      if key is not None:
        r = rows[key]
        out[name] = entry(r["objects_per_s"], "objects/s")
        out["c_peer_" + name] = entry(r["objects"] / r["c_peer_seconds"], "objects/s")
  with open(path, "w") as f:
    json.dump(out, f, indent=1, sort_keys=True)


if __name__ == "__main__":
  app.run(main)
