"""Shape from voxels alone: held-out shape F1 by voxel encoder and number of distinct geometries.

Trains the voxel encoder and generator on geometry (the L1 box loss and the end token,
`losses.loss_fn` with w = 0) exactly as the training loop's geometry stream does
(`training.state.train_step` with no dataset batch), from either the unlimited stream of
fresh towers (`dataset.stream`) or a fixed pool of N towers drawn from it once (with or
without the stream's symmetries of the square as augmentation). Scores shape F1 (IoU >
0.5, the paper's) and the exact box count on towers of a seed no run trains on, drawn by
the NumPy sampler (`ppdjax.sample_towers`) and voxelized by `ppdjax.voxelize`, with 95 %
bootstrap intervals over towers.

  python experiments/shape_study.py --runs=paper_encoder,keep4 --steps=3000
"""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import nnx

import ppdjax
from ppdjax import metrics
from ppdjax.configs import paper
from ppdjax.dataset import stream
from ppdjax.training import state

# name -> voxel_keep, feature and hidden size, distinct geometries (0: the stream), augment,
# and optionally Adam's peak rate (default --lr), global-norm clipping and linear warm-up.
_STABLE = {"clip_norm": 1.0, "warmup_steps": 300}
RUNS = {
    "paper_encoder": dict(keep=1, feature=64, geometries=0, augment=True),
    "paper_encoder_f256": dict(keep=1, feature=256, geometries=0, augment=True),
    "keep4_f64": dict(keep=4, feature=64, geometries=0, augment=True),
    "keep4": dict(keep=4, feature=256, geometries=0, augment=True),
    "keep4_pool4800": dict(keep=4, feature=256, geometries=4_800, augment=True),
    "keep4_pool4800_noaug": dict(keep=4, feature=256, geometries=4_800, augment=False),
    "keep4_pool50k": dict(keep=4, feature=256, geometries=50_000, augment=True),
    # the 256-wide runs above collapsed at 4e-3: a lower rate, clipping and a warm-up
    "paper_encoder_clip": dict(keep=1, feature=64, geometries=0, augment=True, **_STABLE),
    "keep4_f64_clip": dict(keep=4, feature=64, geometries=0, augment=True, **_STABLE),
    "paper_encoder_f256_lr1e-3": dict(keep=1, feature=256, geometries=0, augment=True,
                                      lr=1e-3, **_STABLE),
    "keep4_f256_lr1e-3": dict(keep=4, feature=256, geometries=0, augment=True, lr=1e-3,
                              **_STABLE),
    "keep4_f128_lr2e-3": dict(keep=4, feature=128, geometries=0, augment=True, lr=2e-3,
                              **_STABLE),
}
_RUNS = flags.DEFINE_list("runs", list(RUNS), f"which of {', '.join(RUNS)}; NAME@N trains NAME "
                         "on a fixed pool of N geometries instead (the geometry-count curve)")
_STEPS = flags.DEFINE_integer("steps", 3000, "Adam steps per model")
_BATCH = flags.DEFINE_integer("batch", 256, "batch size")
_LR = flags.DEFINE_float("lr", 4e-3, "Adam's rate, cosine-decayed to 0")
_WIDTH = flags.DEFINE_integer("width", 8, "voxel encoder channel multiplier")
_TEST = flags.DEFINE_integer("test_towers", 1000, "held-out towers")
_TEST_SEED = flags.DEFINE_integer("test_seed", 20261123, "their seed (never trained on)")
_CURVE = flags.DEFINE_integer("curve_points", 4, "held-out F1 evaluations per run")
_SEED = flags.DEFINE_integer("seed", 0, "train.seed (initialisation and stream); rows of a "
                             "seed other than 0 are named NAME#seed")
_OUT = flags.DEFINE_string("out", "experiments/results/shape_study.json", "results JSON")


def study_config(spec: dict):
  keep, feature, augment = spec["keep"], spec["feature"], spec["augment"]
  config = paper.get_config()
  m, t = config.model, config.train
  m.use_image = m.use_trajectory = False
  m.voxel_width, m.voxel_keep, m.feature, m.hidden, m.dropout = _WIDTH.value, keep, feature, \
      feature, 0.0
  t.update(seed=_SEED.value, batch_size=_BATCH.value, learning_rate=spec.get("lr", _LR.value), schedule="cosine",
           stream_steps=_STEPS.value, geometry_steps=0, joint_steps=0, augment=augment,
           clip_norm=spec.get("clip_norm", 0.0), warmup_steps=min(spec.get("warmup_steps", 0), _STEPS.value // 10))
  return config


def held_out():
  prims = ppdjax.sample_towers(_TEST_SEED.value, _TEST.value)
  return jnp.asarray(ppdjax.voxelize(prims)), jax.tree.map(jnp.asarray, prims)


def score(graphdef, st, voxels, prims) -> dict:
  """Held-out F1 and exact box count, each with a 95 % bootstrap interval."""
  @jax.jit
  def counts(st, v, p):
    pred, _ = nnx.merge(graphdef, st).model.decode({"voxels": v})
    return metrics.shape_counts(pred, p)
  parts = [counts(st, voxels[i:i + 250], jax.tree.map(lambda x: x[i:i + 250], prims))
           for i in range(0, len(voxels), 250)]
  c = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}
  f1 = lambda i: metrics.f1_from_counts(c["matched"][i], c["predicted"][i], c["true"][i])
  exact = lambda i: 100.0 * float(np.mean(c["predicted"][i] == c["true"][i]))
  everything = np.arange(len(c["true"]))
  return {"f1": f1(everything), "f1_ci95": metrics.bootstrap_interval(f1, len(everything)),
          "count_exact": exact(everything),
          "count_exact_ci95": metrics.bootstrap_interval(exact, len(everything)),
          "objects": len(everything)}


def row_name(name: str) -> str:
  return name if _SEED.value == 0 else f"{name}#{_SEED.value}"


def spec_of(name: str) -> dict:
  """A run's spec; NAME@N is NAME on a fixed pool of N towers."""
  base, _, pool = name.partition("@")
  return {**RUNS[base], **({"geometries": int(pool)} if pool else {})}


def run(name: str, test) -> dict:
  spec = spec_of(name)
  pool_size, augment = spec["geometries"], spec["augment"]
  config = study_config(spec)
  t = config.train
  graphdef, st = nnx.split(state.build(config))
  if pool_size:  # a fixed pool drawn once from the stream's sampler, then resampled
    pool = stream.geometry_batch(jax.random.key(12345), pool_size, augmented=False)

    def batch_at(i):
      k_idx, k_aug = jax.random.split(jax.random.fold_in(jax.random.key(t.seed), i))
      idx = jax.random.randint(k_idx, (t.batch_size,), 0, pool_size)
      v, p = pool["voxels"][idx], jax.tree.map(lambda x: x[idx], pool["primitives"])
      if augment:
        v, p = stream.augment(k_aug, v, p)
      return {"voxels": v, "primitives": p}
  else:
    batch_at = lambda i: None  # the stream: fresh towers made inside the step
  step = jax.jit(lambda s, i: state.train_step(graphdef, s, batch_at(i), i, 0.0, t),
                 donate_argnums=0)
  curve, losses, start = [], [], time.time()
  marks = {int(round(_STEPS.value * (j + 1) / _CURVE.value)) for j in range(_CURVE.value)}
  for i in range(_STEPS.value):
    st, aux = step(st, jnp.int32(i))
    if (i + 1) % 100 == 0:
      losses.append((i + 1, float(aux["geometry_loss"]), float(aux["end_loss"])))
    if i + 1 in marks:
      s = score(graphdef, st, *test)
      curve.append({"step": i + 1, **s, "seconds": round(time.time() - start, 1)})
      print(f"{name}: step {i + 1} F1 {s['f1']:.1f} [{s['f1_ci95'][0]:.1f}, "
            f"{s['f1_ci95'][1]:.1f}] count exact {s['count_exact']:.1f} % "
            f"({time.time() - start:.0f} s)", flush=True)
  return {"name": row_name(name), "seed": _SEED.value, "voxel_keep": spec["keep"], "feature": spec["feature"],
          "geometries": pool_size or "unlimited", "augment": augment, "steps": _STEPS.value,
          "batch": _BATCH.value, "lr": t.learning_rate, "clip_norm": t.clip_norm,
          "warmup_steps": t.warmup_steps, "width": _WIDTH.value, **curve[-1],
          "curve": curve, "train_losses": losses}


def main(_):
  unknown = {n for n in _RUNS.value if n.partition("@")[0] not in RUNS
             or not n.partition("@")[2].isdigit() and "@" in n}
  if unknown:
    raise app.UsageError(f"unknown runs {sorted(unknown)}; choose from {list(RUNS)}")
  test = held_out()
  results = {"command": "python experiments/shape_study.py " + " ".join(
                 f"--{k}={v}" for k, v in (("runs", ",".join(_RUNS.value)),
                                           ("steps", _STEPS.value), ("batch", _BATCH.value))),
             "device": f"{jax.device_count()} x {jax.devices()[0].device_kind}",
             "test_seed": _TEST_SEED.value, "test_towers": _TEST.value, "rows": []}
  if os.path.exists(_OUT.value):  # rows of other runs stay; a rerun replaces its own
    with open(_OUT.value) as f:
      old = json.load(f)
    results["rows"] = [r for r in old.get("rows", []) if r.get("name") not in map(row_name, _RUNS.value)
                       and "curve" in r]
  for name in _RUNS.value:
    results["rows"].append(run(name, test))
    os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
    with open(_OUT.value, "w") as f:
      json.dump(results, f, indent=1)
  for r in results["rows"]:
    print(f"{r['name']:24s} geometries {str(r['geometries']):>9s}: F1 {r['f1']:.1f} "
          f"[{r['f1_ci95'][0]:.1f}, {r['f1_ci95'][1]:.1f}], count exact {r['count_exact']:.1f} %")


if __name__ == "__main__":
  app.run(main)
