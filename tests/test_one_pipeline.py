"""One pipeline: the evaluation's row of `decompose`'s settings is `decompose`'s answer.

The evaluator runs `decompose`'s stages (`fit_stage`, the candidates drawn from each
object's `object_keys`, the selection, the refinement from the closest candidate) and adds
the tables' rows; these tests run both on the same objects and key and require the same
candidates, the same +Sample pick and the same refined densities.
"""

import jax
import numpy as np
import pytest

from ppdjax.conventions import OBS_KEYS, density_to_slot
from ppdjax.dataset import storage
from ppdjax.eval import baselines
from ppdjax.eval.evaluator import Evaluator
from ppdjax.infer.config import DecomposeConfig, FitConfig, RefineConfig, SelectConfig
from ppdjax.infer.decompose import make_decompose_fn, model_camera, model_settings
from ppdjax.sim.rollout_mjx import MjxSettings
from ppdjax.training import checkpoints

# fewer solver iterations than the dataset's compile faster on a CPU (the box-plane step's
# XLA form took longer); both sides run the same engine, which is what the agreement needs
CHEAP = MjxSettings(iterations=1, ls_iterations=1, push_iterations=2, push_ls_iterations=1)


def _both(trained, config, obs, truth, key, *, camera=None, pushes=None, engine=None):
  """(decompose's Decomposition, the Evaluator's batch output, its records, its headline
  row) on the same objects (a batch) and key."""
  model, run_config = trained
  ev = Evaluator(model, run_config, config, baselines_on=False, camera=camera, pushes=pushes,
                 **({} if engine is None else {"settings": engine}))
  batch = {**obs, "primitives": truth}
  out = ev.batch(batch, None, key)
  slot = baselines.true_slots(truth)
  rec = ev.records(out, slot, slot >= 0, None, prefixes=(1,))
  got = make_decompose_fn(trained, config, camera=camera, pushes=pushes, engine=engine)(obs, key)
  return jax.device_get(got), out, rec, ev.headline_row()


def _check_agreement(got, out, rec, row, refine: bool):
  """decompose's densities are the evaluation's row's, box by box."""
  valid = np.asarray(got.primitives.valid)
  sample_row = row.removesuffix("+Refine")
  if refine:  # the refined densities themselves (the +Sample answer where not closer)
    closer = np.asarray(out["refine"]["closer"], bool)
    assert closer.any()  # else this would test the +Sample pick alone
    np.testing.assert_allclose(np.asarray(got.primitives.density)[closer],
                               np.asarray(out["refine"]["density"])[closer], rtol=1e-5)
    kept = valid & ~closer[:, None]  # boxes where the +Sample answer stays
    picked = density_to_slot(np.asarray(got.primitives.density))
    np.testing.assert_array_equal(picked[kept], np.asarray(rec[("guess", sample_row)])[kept])
  else:  # +Sample's pick: its slots head the row's ranking
    picked = density_to_slot(np.asarray(got.primitives.density))
    np.testing.assert_array_equal(np.where(valid, picked, 0),
                                  np.where(valid, rec[("guess", sample_row)], 0))


@pytest.fixture(scope="module")
def tiny_trained(tiny_run):
  return checkpoints.load(tiny_run[0])


@pytest.mark.slow  # a cross-check: two minutes on 2 cores; `make test-all`
def test_evaluation_and_decompose_agree_on_the_networks_boxes_with_refinement(
    tiny_trained, tiny_dataset):
  """The paper's PPD+Sample+Refine settings (no fit), 4 test towers: the same candidates,
  pick and refined densities."""
  ds = storage.open_dataset(tiny_dataset, "test")
  batch = ds.take(np.arange(4), keys=OBS_KEYS + ("primitives",))
  # refinement by differences: plain rollouts, no forward-mode program to compile
  config = DecomposeConfig(fit=FitConfig(enabled=False), select=SelectConfig(samples=8),
                           refine=RefineConfig(enabled=True, steps=2, jacobian="differences"))
  got, out, rec, row = _both(tiny_trained, config, {k: batch[k] for k in OBS_KEYS},
                             batch["primitives"], jax.random.key(5), pushes=ds.pushes,
                             engine=CHEAP)
  assert row == "PPD+Sample+Refine"
  # candidate by candidate: decompose's distances are the evaluation's network-box group's
  np.testing.assert_allclose(np.asarray(got.scores), out["dist"][:, :8], rtol=1e-5)
  _check_agreement(got, out, rec, row, refine=True)


@pytest.mark.slow  # the image fit and the horizon compile on both sides: minutes on 2 cores
def test_evaluation_and_decompose_agree_with_the_image_fit_and_a_horizon(
    tiny_trained, tiny_dataset):
  ds = storage.open_dataset(tiny_dataset, "test")
  batch = ds.take(np.arange(4), keys=OBS_KEYS + ("primitives",))
  config = DecomposeConfig(fit=FitConfig(image=True), select=SelectConfig(samples=8, horizon=32),
                           refine=RefineConfig(enabled=True, steps=2))
  got, out, rec, row = _both(tiny_trained, config, {k: batch[k] for k in OBS_KEYS},
                             batch["primitives"], jax.random.key(3), camera=ds.camera,
                             pushes=ds.pushes, engine=CHEAP)
  assert row == "PPD+Fit+Sample+Refine"
  np.testing.assert_allclose(np.asarray(got.scores), out["dist"][:, 8:16], rtol=1e-5)
  _check_agreement(got, out, rec, row, refine=True)


@pytest.mark.slow  # the shipped model at 224 x 224 with 512 candidates: minutes on 2 cores
def test_the_shipped_models_defaults_are_its_evaluations_row(tmp_path):
  """`make_decompose_fn("assets/blocks_model")` with no keyword argument is the paper
  preset's evaluation (image fit, 32-step selection, 512 candidates): the same densities
  on the shipped example tower and on fresh towers of a seed never trained on."""
  from ppdjax.configs import paper
  from ppdjax.dataset import generation
  from ppdjax.infer.example import load_example
  trained = checkpoints.load("assets/blocks_model")
  config = model_settings("assets/blocks_model")
  assert config == DecomposeConfig.from_eval(paper.get_config().eval)
  camera = model_camera("assets/blocks_model")
  obs, truth = load_example("assets/blocks_example.npz")
  fresh = paper.get_config()
  fresh.seed = 90_001  # never generated for training
  fresh.data.num_towers, fresh.data.towers_per_shard, fresh.data.configs_per_tower = 1, 1, 3
  fresh.data.split_fractions = (0.0, 0.0, 1.0)
  fresh.data.render_workers = 0
  generation.generate(fresh, str(tmp_path / "fresh"), progress=False)
  test = storage.open_dataset(str(tmp_path / "fresh"), "test")
  more = test.take(np.arange(len(test)), keys=OBS_KEYS + ("primitives",))
  stack = lambda a, b: np.concatenate([np.asarray(a)[None], np.asarray(b)])
  objects = {k: stack(obs[k], more[k]) for k in OBS_KEYS}
  truths = jax.tree.map(stack, truth, more["primitives"])
  key = jax.random.key(0)
  got, out, rec, row = _both(trained, config, objects, truths, key, camera=camera,
                             pushes=test.pushes)
  assert row == "PPD+Fit+Sample"
  default = jax.device_get(make_decompose_fn("assets/blocks_model")(objects, key))
  np.testing.assert_array_equal(default.primitives.density, got.primitives.density)
  _check_agreement(got, out, rec, row, refine=False)
