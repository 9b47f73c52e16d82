"""How well the voxel encoder recovers tower geometry: shape F1 of voxel-only models.

Trains the generator's geometry (paper Eq. 4, w = 0) from voxels alone on freshly sampled
towers (no simulation or rendering needed) and reports shape F1 on held-out towers, for
each voxel-encoder width and feature size given. It isolates the shape half of PPD: the
block pipeline's F1 target (the paper's) is reached or missed here.

  python experiments/shape_study.py --widths=1,8 --steps=2000 --out=experiments/results/shape_study.json
"""

from __future__ import annotations

import json
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import app, flags
from flax import nnx

import ppdjax
from ppdjax import metrics
from ppdjax.configs import tiny
from ppdjax.nn import losses
from ppdjax.nn.model import PPD
from ppdjax.training.state import learning_rate

_WIDTHS = flags.DEFINE_list("widths", ["1", "8"], "voxel encoder channel multipliers")
_FEATURES = flags.DEFINE_integer("feature", 64, "feature and hidden size")
_STEPS = flags.DEFINE_integer("steps", 2000, "Adam steps per model")
_BATCH = flags.DEFINE_integer("batch", 64, "batch size")
_LR = flags.DEFINE_float("lr", 1e-3, "Adam learning rate")
_TRAIN = flags.DEFINE_integer("train_towers", 8000, "distinct training geometries")
_TEST = flags.DEFINE_integer("test_towers", 512, "held-out geometries")
_SCHEDULE = flags.DEFINE_enum("schedule", "constant", ["constant", "cosine"], "Adam's rate")
_COORDS = flags.DEFINE_bool("coords", False, "coordinate channels in the voxel encoder")
_OUT = flags.DEFINE_string("out", "", "JSON file for the results")


def tower_set(seed: int, count: int) -> tuple[np.ndarray, object]:
  prims = ppdjax.sample_towers(seed, count)
  return ppdjax.voxelize(prims), prims


def run(width: int, train, test, steps: int) -> dict:
  config = tiny.get_config().model
  config.use_image = config.use_trajectory = False
  config.voxel_width, config.feature, config.hidden, config.dropout = width, _FEATURES.value, \
      _FEATURES.value, 0.0
  config.voxel_coords = _COORDS.value
  model = PPD(config, rngs=nnx.Rngs(params=0))
  optimizer = nnx.Optimizer(model, optax.adam(learning_rate(ml_collections.ConfigDict(
      {"learning_rate": _LR.value, "schedule": _SCHEDULE.value, "geometry_steps": steps,
       "joint_steps": 0}))), wrt=nnx.Param)
  obs = lambda v: {"voxels": v, "trajectories": jnp.zeros((v.shape[0], 1, 1, 7))}

  @nnx.jit
  def step(model, optimizer, vox, prims):
    tgt = losses.targets(prims)
    def loss(m):
      return losses.loss_fn(m(obs(vox), tgt["prev"], train=True), tgt, 0.0)[0]
    value, grads = nnx.value_and_grad(loss)(model)
    optimizer.update(model, grads)
    return value

  @nnx.jit
  def counts(model, vox, prims):
    pred, _ = model.decode(obs(vox))
    return jax.tree.map(jnp.sum, metrics.shape_counts(pred, prims))

  vox, prims = train
  rng, start, curve = np.random.default_rng(0), time.time(), []
  for i in range(steps):
    idx = rng.integers(0, len(vox), _BATCH.value)
    value = step(model, optimizer, vox[idx], jax.tree.map(lambda x: x[idx], prims))
    if (i + 1) % max(steps // 10, 1) == 0:
      curve.append((i + 1, float(value)))
      print(f"width {width}: step {i + 1} loss {float(value):.3f} ({time.time() - start:.0f} s)")
  c = counts(model, test[0], test[1])
  return {"width": width, "feature": _FEATURES.value, "steps": steps, "batch": _BATCH.value,
          "lr": _LR.value, "schedule": _SCHEDULE.value,
          "coords": _COORDS.value,
          "f1": metrics.f1_from_counts(c["matched"], c["predicted"], c["true"]),
          "train_loss": curve, "seconds": time.time() - start}


def main(_):
  train, test = tower_set(1, _TRAIN.value), tower_set(2, _TEST.value)
  results = [run(int(w), train, test, _STEPS.value) for w in _WIDTHS.value]
  for r in results:
    print(f"width {r['width']} feature {r['feature']} {r['schedule']} batch {r['batch']}: F1 {r['f1']:.1f} after {r['steps']} steps "
          f"({r['seconds']:.0f} s)")
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      json.dump(results, f, indent=1)


if __name__ == "__main__":
  app.run(main)
