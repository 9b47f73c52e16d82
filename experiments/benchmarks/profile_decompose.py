"""Where `decompose`'s time goes: each stage jitted and timed alone, one object and a batch.

  python experiments/benchmarks/profile_decompose.py --samples 512 --batch 64 --out FILE.json

Stages, as `ppdjax.make_decompose_fn` chains them (paper preset network, random weights:
the cost does not depend on them): the network's decode (encoders and the recurrent
generator), `fit_boxes` from the network's boxes, the density draws, the rollouts of every
candidate under the four pushes with scoring, the whole `decompose` (fit on and off), and
`decompose(refine=True)`. Each is a warm jitted call; the median of --repeats. Run it under
different XLA_FLAGS (one process per setting) to compare compiler options.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import nnx

import ppdjax
from ppdjax.configs import paper
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.infer import sampling
from ppdjax.infer.decompose import model_settings
from ppdjax.infer.fit import fit_boxes
from ppdjax.nn.model import PPD
from ppdjax.sim import rollout_mjx

flags.DEFINE_integer("samples", 512, "Density samples per object.")
flags.DEFINE_integer("batch", 64, "Objects in the timed batch.")
flags.DEFINE_integer("repeats", 5, "Warm calls timed (median).")
flags.DEFINE_enum("engine", "box_plane", ["mjx", "box_plane"], "The physics engine.")
flags.DEFINE_enum("kernel", "auto", ["auto", "reference", "pallas"], "The box-plane step's "
                  "kernel (BoxPlaneSettings.kernel).")
flags.DEFINE_string("only", "", "Comma-separated stage-name prefixes.")
flags.DEFINE_string("out", "", "Write the rows as JSON here.")
FLAGS = flags.FLAGS


def timed(fn, repeats: int) -> float:
  jax.block_until_ready(fn())  # compiles
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return float(np.median(times))


def observations(seed: int, count: int, image_size: int, settings) -> dict:
  prims = ppdjax.sample_towers(seed, count)
  rng = np.random.default_rng(seed)
  simulate = lambda p: rollout_mjx.simulate(p, ppdjax.default_pushes(), settings=settings)
  traj = jax.jit(jax.vmap(simulate))(
      jax.tree.map(jnp.asarray, prims))
  return {"voxels": jnp.asarray(ppdjax.voxelize(prims)),
          "image": jnp.asarray(rng.integers(0, 255, (count, image_size, image_size, 3),
                                            np.uint8)),
          "trajectories": traj}


def stages(model, config, samples: int, settings, obs: dict, key) -> dict:
  """{name: fn()} of the stages for these observations, each jitted on its own and fed
  the previous stages' outputs (computed once, outside the timing)."""
  graphdef, state = nnx.split(model)
  pushes = ppdjax.default_pushes()

  @jax.jit
  def decode(obs):
    prims, raw = nnx.merge(graphdef, state).decode(obs)
    return prims, raw.density_logits[:, :prims.num_slots, :NUM_DENSITY_SLOTS]

  @jax.jit
  def draws(logits, valid, key):
    keys = jax.random.split(key, logits.shape[0])
    return jax.vmap(lambda lg, v, k: sampling.candidate_slots(lg, v, samples, k)[0])(
        logits, valid, keys)

  fit = jax.jit(lambda vox, init: fit_boxes(vox, init=init))
  score = jax.jit(jax.vmap(lambda p, s, o: sampling.score_candidates(
      sampling.with_slots(p, s), o, pushes, settings)))
  prims, logits = decode(obs)
  slots = draws(logits, prims.valid, key)
  fns = {"decode (encoders + generator)": lambda: decode(obs),
         "fit_boxes (from the network's)": lambda: fit(obs["voxels"], prims),
         "density draws": lambda: draws(logits, prims.valid, key),
         f"rollouts + scores ({samples} x 4 pushes)": lambda: score(
             prims, slots, obs["trajectories"])}
  shipped = model_settings((model, config)).replace(**{"select.samples": samples})
  for name, kwargs in (("decompose, fit.enabled=False", {"fit.enabled": False,
                                                         "fit.image": False}),
                       ("decompose (the model's settings)", {}),
                       ("decompose, refine.enabled=True", {"refine.enabled": True})):
    fn = ppdjax.make_decompose_fn((model, config), shipped.replace(**kwargs), engine=settings)
    fns[name] = functools.partial(lambda fn: fn(obs, key).score, fn)
  return fns


def main(argv):
  del argv
  config = paper.get_config()
  model = PPD(config.model, rngs=nnx.Rngs(0))
  settings = rollout_mjx.settings_for(FLAGS.engine)
  if FLAGS.engine == "box_plane":
    settings = dataclasses.replace(settings, kernel=FLAGS.kernel)
  obs = observations(0, FLAGS.batch, config.data.image_size, settings)
  one = jax.tree.map(lambda x: x[:1], obs)
  key = jax.random.key(0)
  rows = []
  print(f"| stage | 1 object (ms) | batch of {FLAGS.batch} (ms) | objects/s |\n|---|--:|--:|--:|")
  fns_one = stages(model, config, FLAGS.samples, settings, one, key)
  fns_batch = stages(model, config, FLAGS.samples, settings, obs, key)
  for name in fns_one:
    if FLAGS.only and not any(name.startswith(p) for p in FLAGS.only.split(",")):
      continue
    t1 = timed(fns_one[name], FLAGS.repeats)
    tb = timed(fns_batch[name], max(1, FLAGS.repeats // 2))
    rows.append({"stage": name, "one_ms": t1 * 1e3, "batch_ms": tb * 1e3,
                 "objects_per_s": FLAGS.batch / tb})
    print(f"| {name} | {t1 * 1e3:.1f} | {tb * 1e3:.1f} | {FLAGS.batch / tb:.1f} |", flush=True)
  if FLAGS.out:
    meta = {"device": jax.devices()[0].device_kind, "engine": FLAGS.engine,
            "kernel": FLAGS.kernel,
            "samples": FLAGS.samples, "batch": FLAGS.batch, "jax": jax.__version__,
            "xla_flags": os.environ.get("XLA_FLAGS", "")}
    with open(FLAGS.out, "w") as f:
      json.dump({"meta": meta, "rows": rows}, f, indent=1)


if __name__ == "__main__":
  app.run(main)
