"""Each box's density posterior over +Sample's candidates (`ppdjax.infer.posterior`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppdjax.infer import posterior
from ppdjax.infer.config import DecomposeConfig, PosteriorConfig

INF = float("inf")


def test_weights_follow_the_distance_and_the_prior_and_skip_screened_candidates():
  """log w = log p − (d − d_min) / (scale · d_min), normalised; a screened-out candidate
  (distance inf) weighs nothing; NumPy (the studies) and JAX (decompose) agree."""
  d = np.array([0.010, 0.011, 0.030, INF])
  logp = np.log([0.2, 0.4, 0.3, 0.1])
  w = np.exp(posterior.log_weights(d, logp, 1.0))
  by_hand = np.array([0.2, 0.4 * np.exp(-0.1), 0.3 * np.exp(-2.0), 0.0])
  np.testing.assert_allclose(w, by_hand / by_hand.sum(), rtol=1e-12)
  np.testing.assert_allclose(np.exp(posterior.log_weights(jnp.asarray(d), jnp.asarray(logp),
                                                          1.0)), w, rtol=1e-5, atol=1e-7)
  # a larger scale trusts the motion less: the weights move toward the prior
  flat = np.exp(posterior.log_weights(d, logp, 1e6))
  np.testing.assert_allclose(flat[:3], [0.2 / 0.9, 0.4 / 0.9, 0.3 / 0.9], rtol=1e-4)


def test_marginals_intervals_and_flags_of_a_hand_case():
  """Two boxes and a padded one: the marginals sum to one over the valid boxes' slots (zero
  for padding); the 90 % interval spans the slots holding the central 90 %; a box whose
  candidates agree is identified, one whose candidates spread is not."""
  slots = jnp.array([[10, 40, 0], [10, 50, 0], [10, 60, 0], [11, 70, 0]])
  d = jnp.array([0.01, 0.01, 0.01, 0.01])
  logp = jnp.log(jnp.array([0.3, 0.3, 0.3, 0.1]))
  valid = jnp.array([True, True, False])
  p = posterior.density_posterior(slots, d, logp, valid, scale=1.0, level=0.9,
                                  identified_width=2)
  np.testing.assert_allclose(np.asarray(p.probs).sum(-1), [1.0, 1.0, 0.0], atol=1e-6)
  assert np.asarray(p.probs)[0, 10] == pytest.approx(0.9, abs=1e-6)
  np.testing.assert_allclose(p.mean[:2], [10.1, 40 * 0.3 + 50 * 0.3 + 60 * 0.3 + 70 * 0.1],
                             rtol=1e-6)
  assert (int(p.lower[0]), int(p.upper[0])) == (10, 11)  # 0.9 at 10, the last 0.1 at 11
  assert (int(p.lower[1]), int(p.upper[1])) == (40, 70)
  assert np.asarray(p.identified).tolist() == [True, False, False]
  assert float(p.effective) == pytest.approx(1 / (3 * 0.09 + 0.01), rel=1e-5)


def test_two_boxes_trading_mass_read_a_negative_correlation():
  """Candidates on a ridge (slot a + slot b constant) that explain the motion equally: the
  boxes' slots correlate near -1, and neither is identified."""
  a = jnp.arange(20, 40)
  slots = jnp.stack([a, 80 - a], -1)
  p = posterior.density_posterior(slots, jnp.full(20, 0.02), jnp.zeros(20),
                                  jnp.array([True, True]), scale=1.0, level=0.9,
                                  identified_width=2)
  assert float(p.correlation[0, 1]) == pytest.approx(-1.0, abs=1e-4)
  assert float(p.correlation[0, 0]) == pytest.approx(1.0, abs=1e-4)
  assert not np.asarray(p.identified).any()


def test_posterior_settings_map_the_eval_section_and_bad_ones_are_named():
  cfg = DecomposeConfig.from_eval({"posterior_scale": (0.5, 2.0), "identified_width": 3})
  assert cfg.posterior == PosteriorConfig(scale=(0.5, 2.0), level=0.9, identified_width=3)
  assert PosteriorConfig(scale=0.5).scale == (0.5,)
  assert DecomposeConfig.from_eval(cfg.to_eval()) == cfg
  assert DecomposeConfig.from_dict(cfg.to_dict()) == cfg
  assert cfg.replace(**{"posterior.level": 0.8}).posterior.level == 0.8
  for bad, match in (({"scale": 0.0}, "posterior.scale must be a tuple of finite numbers"),
                     ({"scale": (1.0, float("nan"))}, "posterior.scale"),
                     ({"scale": ()}, "posterior.scale"),
                     ({"level": 1.0}, r"posterior.level must lie in \(0, 1\)"),
                     ({"identified_width": -1}, "identified_width must be a whole number"),
                     ({"identified_width": 1.5}, "identified_width must be a whole number")):
    with pytest.raises(ValueError, match=match):
      DecomposeConfig(posterior=PosteriorConfig(**bad))


def test_the_candidate_pushes_hold_the_papers_four():
  from ppdjax.infer import active  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.pushes import default_pushes  # pylint: disable=import-outside-toplevel
  grid = active.candidate_pushes()
  assert grid.num == 64
  index = active.paper_push_indices(grid, default_pushes())
  assert len(set(index.tolist())) == 4
  np.testing.assert_allclose(np.asarray(grid.sources)[index],
                             np.asarray(default_pushes().sources), atol=1e-5)
  with pytest.raises(ValueError, match="not among the candidates"):
    active.paper_push_indices(active.candidate_pushes(strengths=(0.5,)), default_pushes())


def test_information_gain_is_zero_for_one_motion_and_log_two_for_two_apart():
  """Two equally probable hypotheses: a push under which both move alike gains nothing;
  one under which they move far apart (distance >> T) gains log 2 nats, the posterior's
  whole entropy. MuJoCo's C engine simulates them (a CPU's engine)."""
  from ppdjax.dataset.towers import sample_towers  # pylint: disable=import-outside-toplevel
  from ppdjax.infer import active  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.rollout_mujoco import MujocoSettings  # pylint: disable=import-outside-toplevel
  tower = jax.tree.map(lambda x: x[0], sample_towers(3, 1, num_blocks=2))
  pushes = active.candidate_pushes(azimuths=2, elevations=(0.0,), strengths=(1.0,))
  gain = jax.jit(lambda slots, distance: active.push_gains(  # one program, not op by op
      tower, slots, distance, jnp.zeros(2), pushes, hypotheses=2, scale=1.0, steps=64,
      settings=MujocoSettings()).gain)
  gains = lambda slots, distance: np.asarray(gain(jnp.asarray(slots),  # noqa: E731
                                                  jnp.asarray(distance, jnp.float32)))
  same = np.array([[20, 20, 0, 0, 0], [20, 20, 0, 0, 0]])
  np.testing.assert_allclose(gains(same, [0.01, 0.01]), 0.0, atol=1e-3)  # d_ii: 1e-6 m
  apart = np.array([[0, 0, 0, 0, 0], [99, 99, 0, 0, 0]])  # 100 against 10,000 kg/m3
  np.testing.assert_allclose(gains(apart, [1e-5, 1e-5]), np.log(2.0), rtol=1e-3)


def test_repeated_candidates_weigh_nothing_and_no_finite_distance_leaves_the_prior():
  """A repeat of an earlier candidate (a small support) is counted once, not twice; an
  object whose every candidate failed (distance inf or NaN) reads its prior, not NaN."""
  slots = jnp.array([[10], [12], [10]])
  d = jnp.full(3, 0.01)
  logp = jnp.log(jnp.array([0.5, 0.5, 0.5]))
  valid = jnp.array([True])
  once = posterior.density_posterior(slots, d, logp, valid, scale=1.0, level=0.9,
                                     identified_width=2,
                                     distinct_S=jnp.array([True, True, False]))
  assert float(once.probs[0, 10]) == pytest.approx(0.5, abs=1e-6)
  failed = posterior.density_posterior(slots[:2], jnp.array([INF, float("nan")]),
                                       jnp.log(jnp.array([0.8, 0.2])), valid, scale=1.0,
                                       level=0.9, identified_width=2)
  np.testing.assert_allclose(np.asarray(failed.probs)[0, [10, 12]], [0.8, 0.2], atol=1e-6)
  # one candidate alone says nothing of how sure it is
  alone = posterior.density_posterior(slots[:1], d[:1], logp[:1], valid, scale=1.0,
                                      level=0.9, identified_width=2)
  assert not bool(alone.identified[0])


def test_a_scale_per_box_count_is_read_by_the_objects_own_count():
  """`scale` (1, 2, ... boxes): a 2-box object takes the second entry, a 5-box object past
  the table's end its last."""
  two = jnp.array([True, True, False, False, False])
  assert float(posterior.scale_for((0.1, 0.2, 0.3), two)) == pytest.approx(0.2)
  assert float(posterior.scale_for((0.1, 0.2, 0.3), jnp.ones(5, bool))) == pytest.approx(0.3)
  assert posterior.scale_for(0.7, two) == 0.7
