"""+Search (`infer.search`): the draw iterated near the closest candidates, and its settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax.configs import tiny
from ppdjax.conventions import slot_to_density
from ppdjax.configs.schema import ConfigError
from ppdjax.dataset import towers
from ppdjax.infer import sampling, search
from ppdjax.infer.config import DecomposeConfig

PUSHES = ppdjax.default_pushes()


def stand_in_simulate(prims, pushes, *, steps, settings):
  """A motion that reads every box's log density (x) and inertia scale (y) smoothly: one
  basin in the slots and the levels, as a glued tower's mass properties give."""
  del settings
  t = jnp.arange(steps)[:, None] * (jnp.arange(prims.valid.shape[0]) + 1.0)
  live = jnp.where(prims.valid, 1.0, 0.0)
  log_density = jnp.log(jnp.where(prims.valid, prims.density, 1e3) / 1e3)
  x = 1e-2 * (jnp.sin(0.3 * t) * log_density * live).sum(-1)
  scale = 1.0 if prims.inertia_scale is None else prims.inertia_scale
  y = 1e-2 * (jnp.cos(0.4 * t) * jnp.log(scale) * live).sum(-1)
  pose = jnp.concatenate([jnp.stack([x, y, 0 * x], -1), jnp.tile(jnp.array(
      [1.0, 0, 0, 0]), (steps, 1))], -1)
  return jnp.broadcast_to(pose, (pushes.num, steps, 7))


@pytest.fixture(name="tower")
def _tower(monkeypatch):
  """Four boxes at slots far from where the scores point, two of them hollow; the
  stand-in simulator in place of the engine."""
  monkeypatch.setattr(sampling, "simulate", stand_in_simulate)
  truth = jax.tree.map(lambda x: jnp.asarray(x[0]), towers.sample_towers(1, 1, num_blocks=4))
  slots = jnp.where(truth.valid, jnp.array([12, 70, 33, 88, 0]), 0)
  levels = jnp.asarray(search.INERTIA_LEVELS)
  scale = jnp.where(truth.valid, jnp.array([1.0, levels[6], 1.0, levels[2], 1.0]), 1.0)
  truth = truth.replace(density=jnp.asarray(slot_to_density(np.asarray(slots)), jnp.float32),
                        inertia_scale=scale)
  observed = stand_in_simulate(truth, PUSHES, steps=48, settings=None)
  logits = jnp.zeros((5, 100)).at[:, 50].set(3.0)  # scores sure of the wrong slot
  return truth, slots, observed, logits


def test_search_finds_what_one_draw_of_as_many_candidates_misses(tower):
  truth, slots, observed, logits = tower
  run = lambda rounds, samples, inertia: jax.jit(  # noqa: E731
      lambda p, l, o: search.search_densities(
          p, l, o, PUSHES, num_samples=samples, rounds=rounds, key=jax.random.key(0),
          inertia=inertia))(truth.replace(inertia_scale=None), logits, observed)
  v = np.asarray(truth.valid)
  rounds, once = run(4, 256, True), run(1, 1024, True)
  assert rounds.scores.shape == (1024,) and rounds.slots.shape == (1024, 5)
  assert float(rounds.score) < 0.5 * float(once.score)
  found = np.asarray(rounds.density)[v] / np.asarray(truth.density)[v]
  assert np.all(np.abs(np.log(found)) < 0.1), found  # within 10 % (a slot near 1,000 kg/m³)
  scale = np.asarray(rounds.boxes.inertia_scale[rounds.best])
  step = np.log(search.INERTIA_LEVELS[1] / search.INERTIA_LEVELS[0])
  assert np.all(np.abs(np.log(scale[v] / np.asarray(truth.inertia_scale)[v])) < 1.01 * step)
  # the winner is the least of the returned scores, its trajectory the winner's
  assert float(rounds.score) == pytest.approx(float(rounds.scores.min()), rel=1e-5)
  winner = jax.tree.map(lambda x: x[rounds.best], rounds.boxes)
  np.testing.assert_allclose(rounds.trajectories, stand_in_simulate(
      winner, PUSHES, steps=48, settings=None), atol=1e-6)
  # without inertia the boxes stay as given (no scales); across rounds a repeat is flagged,
  # the first of its kind is not
  solid = run(4, 64, False)
  assert solid.boxes.inertia_scale is None
  codes = [tuple(r) for r in np.asarray(solid.slots)]
  first = {c: i for i, c in reversed(list(enumerate(codes)))}
  np.testing.assert_array_equal(np.asarray(solid.distinct),
                                [first[c] == i for i, c in enumerate(codes)])
  assert not np.asarray(solid.distinct).all()  # later rounds draw near the elite, again


def test_repeats_flag_every_later_copy():
  rows = jnp.array([[3, 4], [5, 6], [3, 4], [7, 8], [5, 6], [3, 4]])
  np.testing.assert_array_equal(sampling.repeats(rows, 100),
                                [False, False, True, False, True, True])


def test_search_settings_are_checked():
  cfg = DecomposeConfig().replace(**{"select.rounds": 4, "select.inertia": True})
  assert cfg.select.searches
  assert DecomposeConfig.from_eval(cfg.to_eval()) == cfg  # the eval section carries both
  for bad in (0, 1.5, True):
    with pytest.raises(ConfigError, match="select.rounds"):
      DecomposeConfig().replace(**{"select.rounds": bad})
  with pytest.raises(ConfigError, match="select.inertia must be"):
    DecomposeConfig().replace(**{"select.inertia": "yes"})
  with pytest.raises(ConfigError, match="without select.mass_match"):
    DecomposeConfig().replace(**{"select.rounds": 2, "select.mass_match": True})
  with pytest.raises(ConfigError, match="without select.mass_match"):
    DecomposeConfig().replace(**{"select.inertia": True, "select.screen_steps": 32})
  with pytest.raises(ConfigError, match="needs select.rounds > 1"):
    DecomposeConfig().replace(**{"select.continuation": 16})
  for bad in (-1, 2.5):
    with pytest.raises(ConfigError, match="select.continuation must be"):
      DecomposeConfig().replace(**{"select.rounds": 4, "select.continuation": bad})
  cfg = cfg.replace(**{"select.continuation": 16})
  assert DecomposeConfig.from_eval(cfg.to_eval()) == cfg
  e = tiny.get_config().eval
  assert not DecomposeConfig.from_eval(e).select.searches  # off by default
  assert DecomposeConfig.from_eval(e).select.continuation == 0


def test_continuation_doubles_each_rounds_horizon_up_to_the_selections():
  with pytest.raises(ConfigError, match="shorter than select.horizon"):
    DecomposeConfig().replace(**{"select.rounds": 4, "select.continuation": 32,
                                 "select.horizon": 32})
  assert search.continuation_horizons(16, 6, 0, 256) == (16, 32, 64, 128, 0, 0)
  assert search.continuation_horizons(16, 5, 100, 256) == (16, 32, 64, 100, 100)
  assert search.continuation_horizons(0, 3, 32, 256) == (32, 32, 32)


def test_search_with_a_continuation_still_finds_the_densities(tower):
  """Elites chosen over 8, 16, 32 steps and then all 48: the winner, the least over every
  step, is as close as without the schedule, and the densities within 10 %."""
  truth, slots, observed, logits = tower
  del slots
  run = lambda continuation: jax.jit(lambda p, l, o: search.search_densities(  # noqa: E731
      p, l, o, PUSHES, num_samples=256, rounds=5, key=jax.random.key(0),
      continuation=continuation))(truth.replace(inertia_scale=None), logits, observed)
  plain, scheduled, past_the_end = run(0), run(8), run(48)
  # a schedule that starts at the whole trajectory is no schedule: the same search
  np.testing.assert_array_equal(np.asarray(past_the_end.slots), np.asarray(plain.slots))
  v = np.asarray(truth.valid)
  found = np.asarray(scheduled.density)[v] / np.asarray(truth.density)[v]
  assert np.all(np.abs(np.log(found)) < 0.1), found
  assert float(scheduled.score) == pytest.approx(float(scheduled.scores.min()), rel=1e-5)
  assert float(scheduled.score) < 2.0 * float(plain.score) + 1e-4
  # the schedule changes which candidates later rounds draw near (not only the winner)
  assert not np.array_equal(np.asarray(plain.slots[256:]), np.asarray(scheduled.slots[256:]))
