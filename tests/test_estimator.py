"""The density estimator: its training data, the model, training, saving and evaluation."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from ppdjax.configs import tiny
from ppdjax.dataset import physics_stream
from ppdjax.dataset.materials import MATERIAL_NAMES, material_slots
from ppdjax.nn.estimator import DensityEstimator, combine_logits, slot_targets
from ppdjax.sim.pushes import default_pushes, pendulum_strike
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS
from ppdjax.sim.simulate import simulate
from ppdjax.training import estimator as est
from ppdjax.training.checkpoints import CheckpointError

STEPS_IN = 32  # short pools keep the CPU simulation cheap


def small_config(steps_in=STEPS_IN, **overrides):
  config = tiny.get_config()
  e = config.estimator
  e.pool_size, e.val_size, e.steps, e.eval_every, e.steps_in = 64, 64, 12, 6, steps_in
  e.batch_size, e.warmup_steps = 16, 2
  e.update(overrides)
  return config


@pytest.fixture(scope="module")
def batch():
  """64 objects: the shape `train_estimator`'s 64-object pools compile, so it is compiled once."""
  return physics_stream._physics_batch_jit(jax.random.key(3), default_pushes(), batch=64,
                                           steps=STEPS_IN, settings=DEFAULT_SETTINGS)


def test_slots_follow_the_materials():
  valid = jnp.ones((400, 5), bool).at[:, 3:].set(False)
  mats, slots = physics_stream.sample_slots_jax(jax.random.key(0), valid)
  mats, slots = np.asarray(mats), np.asarray(slots)
  assert set(np.unique(mats[:, :3])) == set(range(len(MATERIAL_NAMES)))
  assert np.all(mats[:, 3:] == -1) and np.all(slots[:, 3:] == 0)
  for m, s in zip(mats[:, :3].ravel(), slots[:, :3].ravel()):
    assert s in material_slots(MATERIAL_NAMES[m])


@pytest.mark.slow  # compiles an MJX rollout (about 30 s on 2 cores)
def test_physics_batch_is_the_simulation_of_its_boxes(batch):
  """Its trajectories are its boxes' under the paper's pushes: MuJoCo C (no compilation)
  agrees to a few mm over the first 0.1 s (docs/physics.md: p90 0.09 mm)."""
  prims, traj = batch["primitives"], batch["trajectories"]
  assert traj.shape == (64, 4, STEPS_IN, 7) and np.all(np.isfinite(traj))
  np.testing.assert_allclose(prims.density[prims.valid],
                             (batch["slots"][prims.valid] + 1) * 100.0)
  some = jax.tree.map(lambda x: np.asarray(x[:6]), prims)
  c = simulate(some, steps=STEPS_IN, backend="mujoco")
  moved = np.abs(np.asarray(traj[:6, :, -1, :3] - traj[:6, :, 0, :3])).max()
  assert moved > 0.01  # the pushes move them
  np.testing.assert_allclose(c[..., :3], traj[:6, ..., :3], atol=5e-3)


@pytest.mark.slow  # about 8 s on 2 cores; `make test-all` (the fast suite stays under 10 minutes)
def test_estimator_reads_boxes_in_any_order():
  e = small_config().estimator
  model = DensityEstimator(e, rngs=nnx.Rngs(params=0))
  prims = physics_stream.sample_towers_jax(jax.random.key(1), 8)  # no simulation needed:
  traj = jax.random.normal(jax.random.key(2), (8, 4, STEPS_IN, 7))  # any motion will do
  run = nnx.jit(lambda m, p, t: m(p, t))  # one compilation instead of op-by-op dispatch
  logits = run(model, prims, traj)
  assert logits.shape == (8, 5, 100)
  assert np.all(np.asarray(logits)[~np.asarray(prims.valid)] == 0)
  perm = jnp.array([4, 2, 0, 3, 1])
  shuffled = jax.tree.map(lambda x: x[:, perm], prims)
  np.testing.assert_allclose(run(model, shuffled, traj), logits[:, perm], atol=1e-5)
  with pytest.raises(ValueError, match="trajectories"):
    model(prims, traj[:, :, :-1])


def test_targets_and_combination():
  t = slot_targets(jnp.array([[0, 50]]), 1.0)
  np.testing.assert_allclose(t.sum(-1), 1.0, rtol=1e-6)
  assert int(jnp.argmax(t[0, 1])) == 50 and float(t[0, 1, 49]) > 0.1
  np.testing.assert_array_equal(slot_targets(jnp.array([3]), 0.0)[0], jax.nn.one_hot(3, 100))
  a, b = jax.random.normal(jax.random.key(0), (2, 5, 100))
  np.testing.assert_allclose(combine_logits(a, b, 0.0), jax.nn.log_softmax(a), atol=1e-6)


@pytest.mark.slow  # simulates its pools in MJX (about a minute on 2 cores)
def test_train_resume_save_and_load(tmp_path, batch):
  config = small_config()
  work = str(tmp_path / "est")
  first = est.train_estimator(config, work, max_seconds=1e-9, progress=False)
  assert not first["done"] and first["step"] < config.estimator.steps
  assert os.path.exists(os.path.join(work, est.RESUME))
  with pytest.raises(CheckpointError, match="did not finish"):
    est.load(work)
  done = est.train_estimator(config, work, progress=False)
  assert done["done"] and done["step"] == config.estimator.steps
  rows = [json.loads(line) for line in open(os.path.join(work, est.METRICS))]
  assert rows[0]["step"] == first["step"] and rows[-1]["step"] == config.estimator.steps
  assert {"val_top1", "val_rmse", "loss"} <= set(rows[-1])
  model, e = est.load(work)
  assert tuple(e.channels) == tuple(config.estimator.channels)
  some = jax.tree.map(lambda x: x[:4], batch["primitives"])
  assert np.all(np.isfinite(model(some, batch["trajectories"][:4])))
  other = small_config(hidden=32)
  with pytest.raises(ValueError, match="another config"):
    est.train_estimator(other, work, progress=False)
  with open(os.path.join(work, est.WEIGHTS), "r+b") as f:
    f.seek(100)
    f.write(b"\0" * 16)
  with pytest.raises(CheckpointError, match="corrupt"):
    est.load(work)
  with pytest.raises(CheckpointError, match="no trained density estimator"):
    est.load(str(tmp_path))
  with pytest.raises(ValueError, match="box_noise"):
    est.train_estimator(small_config(box_noise=-1.0), str(tmp_path / "bad"), progress=False)


@pytest.mark.slow
def test_evaluation_adds_the_estimator_rows(tiny_run, tiny_dataset, tmp_path):
  """A tiny estimator (the dataset's 256 steps) joins the evaluation: the +Est rows on the
  fitted boxes, refinement from them, and the estimator's own arg-max row."""
  from ppdjax.eval import evaluation, groups
  config = small_config(steps_in=tiny.get_config().data.steps, pool_size=32, val_size=32,
                        steps=4, eval_every=4)
  work = str(tmp_path / "est")
  est.train_estimator(config, work, progress=False)
  from ppdjax.infer.config import FitConfig
  with pytest.raises(ValueError, match="needs fit.enabled"):
    groups.fit_groups(FitConfig(enabled=False), estimator=True)
  assert groups.fit_groups(FitConfig(depth=True), True) == ("fit_depth", "fit_depth_est")
  results = evaluation.evaluate(tiny_run[0], tiny_dataset, samples=4, max_objects=4,
                                fit=True, refine=True, refine_steps=1, baselines=False,
                                estimator=work, estimator_weight=0.5, joint=True,
                                true_shapes=True, progress=False)
  rows = results["table2"]
  for name in ("PPD+Fit+Est", "PPD+Fit+Est+Sample", "PPD+Fit+Est+Sample+Refine", "Estimator"):
    assert name in rows, name
  assert rows["Estimator"]["mae"] is None and rows["PPD+Fit+Est+Sample"]["mae"] > 0
  assert "PPD+Fit+Sample+Refine" not in rows  # refinement starts from the +Est group
  assert rows["PPD+Fit+Est+Sample+Joint"]["mae"] > 0  # so does +Joint
  assert results["face_error_mm"]["joint"]["faces"] > 0
  # the oracle rows on the true boxes, refined alike; F1 100 by construction
  assert rows["PPD+True boxes+Sample+Refine"]["mae"] > 0 and results["f1_true"] == 100.0
  assert rows["PPD+True boxes"]["top1"] == rows["PPD"]["top1"]  # the network's scores
  assert results["f1_fit_est"] == results["f1_fit"]
  assert results["estimator"] == work and results["estimator_weight"] == 0.5
  assert results["headline"] == "PPD+Fit+Est+Sample+Refine"


def test_decompose_checks_the_estimator_settings():
  from ppdjax.infer.config import DecomposeConfig, EstimatorConfig, FitConfig
  from ppdjax.infer.decompose import make_decompose_fn
  with pytest.raises(ValueError, match="needs fit.enabled"):
    DecomposeConfig(fit=FitConfig(enabled=False), estimator=EstimatorConfig(path="anything"))
  weaker = default_pushes(magnitude=1e3)  # the tools' strength
  with_estimator = DecomposeConfig(estimator=EstimatorConfig(path="anything"))
  for pushes in (pendulum_strike(), weaker):
    with pytest.raises(ValueError, match="paper's four pushes"):
      make_decompose_fn((None, tiny.get_config()), with_estimator, pushes=pushes)
