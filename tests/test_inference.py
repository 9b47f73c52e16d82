"""Inference: density sampling, refinement through the simulator, decompose and its errors."""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import metrics
from ppdjax.configs import tiny
from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import storage, towers
from ppdjax.infer import refine, sampling, search
from ppdjax.infer.config import DecomposeConfig, FitConfig, RefineConfig, SelectConfig
from ppdjax.report import tables
from ppdjax.primitives import quat_mul
from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, MjxSettings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PUSHES = ppdjax.default_pushes()
SAMPLES = tiny.get_config().eval.samples  # the demo's, so compilations are shared


def _simulate(prims):
  return ppdjax.simulate(prims, PUSHES)  # the compiled rollouts the demo's tour uses too


def test_candidates_keep_the_mode_and_have_no_duplicates(rng):
  logits = jnp.asarray(rng.normal(size=(5, 100)), jnp.float32)
  valid = jnp.array([True, True, True, False, False])
  slots, distinct = sampling.candidate_slots(logits, valid, 64, jax.random.key(0))
  assert slots.shape == (64, 5) and bool(distinct.all())
  np.testing.assert_array_equal(slots[0, :3], jnp.argmax(logits, -1)[:3])
  assert not np.asarray(slots[:, 3:]).any()  # padded boxes
  assert len({tuple(r) for r in np.asarray(slots)}) == 64
  # support of 2 x 2 assignments: 4 distinct ones come first, then repeats flagged
  small = jnp.full((5, 100), -1e9).at[:, 7].set(0.0).at[:, 40].set(0.0)
  slots, distinct = sampling.candidate_slots(small, valid.at[2].set(False), 8,
                                              jax.random.key(1))
  assert list(np.asarray(distinct)) == [True] * 4 + [False] * 4
  assert len({tuple(r) for r in np.asarray(slots[:4])}) == 4


def test_face_errors_on_a_hand_case():
  from ppdjax.primitives import Primitives
  box = lambda pos, half, valid: Primitives(
      half_size=jnp.asarray(half, jnp.float32), pos=jnp.asarray(pos, jnp.float32),
      quat=jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (2, 1)), density=jnp.ones(2),
      valid=jnp.asarray(valid))
  true = box([[0, 0, -0.2], [0, 0, 0.2]], [[0.1, 0.1, 0.2]] * 2, [True, True])
  pred = box([[0.01, 0, -0.2], [0, 0, 0.2]], [[0.1, 0.1, 0.21], [0.1, 0.1, 0.2]], [True, False])
  err = np.asarray(metrics.face_errors(pred, true))
  np.testing.assert_allclose(err[0], [0.01, 0, 0.01, 0.01, 0, 0.01], atol=1e-6)
  assert np.isnan(err[1]).all()  # a missing box has no faces
  s = tables.face_summary(err[None])
  assert s["faces"] == 6 and abs(s["max"] - 10.0) < 1e-3 and abs(s["median_by_face"]["y lo"]) < 1e-3


def test_trajectory_metrics_on_hand_cases():
  obs = jnp.zeros((2, 3, 7)).at[..., 3].set(1.0)
  sim = obs.at[..., 0].add(0.003).at[..., 2].add(-0.006)  # 3 mm, -6 mm
  assert float(metrics.trajectory_mae(sim, obs)) == pytest.approx(3.0, rel=1e-5)
  assert float(metrics.trajectory_distance(sim, obs)) == pytest.approx(
      np.hypot(0.003, 0.006), rel=1e-4)
  half = jnp.array([np.cos(0.05), 0.0, 0.0, np.sin(0.05)])  # 0.1 rad about z
  r = metrics.pose_residual(obs.at[..., 3:].set(half), obs)
  np.testing.assert_allclose(r[0, 0], [0, 0, 0, 0, 0, 0.1 * metrics.ROTATION_LENGTH],
                             atol=1e-6)
  q = jnp.asarray(np.random.default_rng(0).normal(size=(10, 4)), jnp.float32)
  q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
  np.testing.assert_allclose(metrics.rotation_vector(quat_mul(q, q * jnp.array(
      [1.0, -1, -1, -1]))), 0.0, atol=1e-3)
  np.testing.assert_allclose(metrics.rotation_vector(-q), metrics.rotation_vector(q),
                             atol=1e-5)
  # over the first h steps: errors of 1, 2, 3 mm at steps 0, 1, 2 (both pushes)
  grow = obs.at[..., 0].add(0.001 * jnp.arange(1, 4)[None, :])
  d = metrics.horizon_distances(grow, obs, (1, 2, 0, 99))
  np.testing.assert_allclose(d, [0.001, 0.0015, 0.002, 0.002], rtol=1e-4)
  assert float(metrics.trajectory_distance(grow, obs, horizon=2)) == pytest.approx(0.0015,
                                                                                  rel=1e-4)


@pytest.fixture(scope="module")
def tower():
  """A two-block tower that moves under the pushes, and its trajectories observed in MuJoCo
  C (cheap to compile; the selections below use the engine they name)."""
  prims = jax.tree.map(jnp.asarray, towers.sample_towers(3, 1, num_blocks=2))
  observed = ppdjax.simulate(jax.tree.map(np.asarray, prims), PUSHES, backend="mujoco")
  return jax.tree.map(lambda x: x[0], prims), jnp.asarray(observed[0], jnp.float32)


def test_sampling_finds_the_truth_when_the_prior_contains_it(tower):
  """On the C engine, `decompose`'s on a CPU (MJX's selection: the cross-check below)."""
  from ppdjax.sim.rollout_mujoco import MujocoSettings
  prims, observed = tower
  true = np.asarray(jnp.rint(prims.density / 100.0) - 1).astype(int)
  logits = jnp.full((5, 100), -1e9)
  for k in range(2):  # support {t - 3, t, t + 3}; the mode (t + 3) is wrong
    t = true[k]
    logits = logits.at[k, t - 3].set(0.0).at[k, t].set(0.5).at[k, t + 3].set(1.0)
  sel = jax.jit(lambda p, lg, o, key: sampling.select_densities(
      p, lg, o, PUSHES, num_samples=16, key=key, settings=MujocoSettings()))(
          prims, logits, observed, jax.random.key(0))
  np.testing.assert_allclose(sel.density[:2], prims.density[:2])
  assert float(sel.score) < 1e-5 and float(sel.scores[0]) > 1e-4
  distinct = np.asarray(sel.slots)[np.asarray(sel.distinct)]
  assert 7 <= len(distinct) == len({tuple(r) for r in distinct}) <= 9  # of the 9 in support


@pytest.mark.slow  # a cross-check: compiles the selection on MJX (about 40 s on 2 cores)
def test_the_cpu_engine_picks_the_candidate_the_jax_engine_picks():
  """MuJoCo C inside the jitted selection (`MujocoSettings`, `decompose`'s engine on a
  CPU) against MJX (the JAX engine) on three towers observed in MJX: the same winner among
  the same 16 candidates, and each candidate's distance within the engines' gap (MJX
  departs from C by millimetres to centimetres after a box lands: docs/physics.md)."""
  from ppdjax.sim.rollout_mujoco import MujocoSettings
  for seed in (3, 11, 12):
    prims = jax.tree.map(jnp.asarray, towers.sample_towers(seed, 1, num_blocks=2))
    prims, observed = jax.tree.map(lambda x: x[0], prims), _simulate(prims)[0]
    true = np.asarray(jnp.rint(prims.density / 100.0) - 1).astype(int)
    logits = jnp.full((5, 100), -1e9)
    for k in range(2):  # as the test above
      t = true[k]
      logits = logits.at[k, t - 3].set(0.0).at[k, t].set(0.5).at[k, t + 3].set(1.0)
    run = lambda settings: jax.jit(lambda p, lg, o, key: sampling.select_densities(
        p, lg, o, PUSHES, num_samples=16, key=key, **settings))(
            prims, logits, observed, jax.random.key(0))
    mjx, c = run({}), run({"settings": MujocoSettings()})
    assert int(c.best) == int(mjx.best), seed
    np.testing.assert_allclose(c.density, mjx.density)
    np.testing.assert_array_equal(c.slots, mjx.slots)
    np.testing.assert_allclose(c.scores, mjx.scores, atol=0.02)  # metres, mean over steps


@pytest.mark.slow  # a second decompose program at another horizon (~25 s on 2 cores); the
# horizon's pick on hand-made distances stays in the default run (test_evaluation)
def test_a_horizon_simulates_the_candidates_that_far_for_the_same_pick(tower):
  """`whole_scores=False` (decompose without refinement): the candidates are simulated over
  the selection horizon only, the winner over every step: the same pick, score and
  trajectories as simulating every candidate whole (on the C engine: cheap to compile)."""
  from ppdjax.sim.rollout_mujoco import MujocoSettings
  prims, observed = tower
  logits = jnp.zeros((5, 100))  # every slot equally likely: 32 spread-out candidates
  run = lambda whole: jax.jit(lambda p, lg, o, key: sampling.select_densities(
      p, lg, o, PUSHES, num_samples=32, key=key, selection_horizon=24, whole_scores=whole,
      settings=MujocoSettings()))(prims, logits, observed, jax.random.key(2))
  whole, short = run(True), run(False)
  assert int(short.best) == int(whole.best)
  np.testing.assert_allclose(short.density, whole.density)
  np.testing.assert_allclose(short.score, whole.score, rtol=1e-6)
  np.testing.assert_allclose(short.trajectories, whole.trajectories, atol=1e-6)
  sims = ppdjax.simulate(jax.tree.map(np.asarray, short.boxes), PUSHES, steps=24,
                         backend="mujoco")  # (S, P, 24, 7): the distance over the horizon
  np.testing.assert_allclose(short.scores, metrics.trajectory_distance(
      jnp.asarray(sims, jnp.float32), observed[:, :24]), rtol=1e-5, atol=1e-7)


@pytest.mark.slow  # compiles a second sampling call
def test_faces_drawn_with_the_densities_are_returned_with_the_winner(tower):
  """`face_spread`: every candidate's boxes come back (candidate 0 the given ones, the
  others moved within the spread); the winner's densities and score are those of
  candidate `best`, re-simulated."""
  prims, observed = tower
  true = np.asarray(jnp.rint(prims.density / 100.0) - 1).astype(int)
  logits = jnp.full((5, 100), -1e9)
  for k in range(2):
    logits = logits.at[k, true[k] - 3].set(0.0).at[k, true[k]].set(0.5)
  sel = jax.jit(lambda p, lg, o, key: sampling.select_densities(
      p, lg, o, PUSHES, num_samples=8, key=key, face_spread=0.5))(prims, logits, observed,
                                                                jax.random.key(1))
  boxes = jax.tree.map(np.asarray, sel.boxes)
  np.testing.assert_allclose(boxes.half_size[0], prims.half_size, atol=1e-6)
  moved = np.abs(boxes.half_size[1:] - np.asarray(prims.half_size)).max((-1, -2))
  assert np.all(moved > 0) and np.all(moved < 1 / 32)
  best = int(sel.best)
  np.testing.assert_allclose(sel.density, boxes.density[best])
  again = _simulate(jax.tree.map(lambda x: jnp.asarray(x[best])[None], boxes))[0]
  assert float(metrics.trajectory_distance(again, observed)) == pytest.approx(
      float(sel.score), rel=1e-4, abs=1e-7)
  assert float(sel.score) == pytest.approx(float(np.min(sel.scores)), abs=1e-9)


def test_decompose_config_maps_the_eval_section_and_names_bad_settings():
  """`DecomposeConfig.from_eval` is the one mapping from a preset's eval section; its
  presets are the paper's inputs and the depth + refinement settings."""
  from ppdjax.configs import paper  # pylint: disable=import-outside-toplevel
  from ppdjax.configs.schema import ConfigError  # pylint: disable=import-outside-toplevel
  cfg = DecomposeConfig.from_eval(paper.get_config().eval)
  assert cfg.fit == FitConfig(enabled=True, image=True) and cfg.select.horizon == 32
  assert cfg.select.samples == 512 and not cfg.refine.enabled
  assert DecomposeConfig.from_eval(cfg.to_eval()) == cfg
  assert DecomposeConfig.from_dict(cfg.to_dict()) == cfg
  assert DecomposeConfig.paper().fit == cfg.fit and DecomposeConfig.paper().select == cfg.select
  best = DecomposeConfig.best()
  assert best.fit.depth and best.refine.enabled and best.fit.with_ == ("depth",)
  assert best.posterior.scale != DecomposeConfig().posterior.scale  # its own calibration
  assert DecomposeConfig.from_eval(best.to_eval()) == best
  assert DecomposeConfig.from_dict(best.to_dict()) == best
  assert cfg.replace(**{"select.samples": 8}).select.samples == 8
  with pytest.raises(ValueError, match="no part 'sample'"):
    cfg.replace(**{"sample.samples": 8})
  with pytest.raises(ValueError, match="no setting 'sample'"):
    cfg.replace(**{"select.sample": 8})
  with pytest.raises(ValueError, match="need fit.enabled"):
    DecomposeConfig(fit=FitConfig(enabled=False, image=True))
  with pytest.raises(ValueError, match="samples must be a whole number >= 1"):
    DecomposeConfig(select=SelectConfig(samples=0))
  with pytest.raises(ConfigError, match="config.eval has no key sample"):
    DecomposeConfig.from_eval({"sample": 3})
  with pytest.raises(ConfigError, match="config.eval.samples must be a whole number"):
    DecomposeConfig.from_eval({"samples": "many"})
  # +Sample's τ by box source: the network's own boxes may have their own
  own = DecomposeConfig.from_eval({"prior_weight": 0.0, "network_prior_weight": 0.002})
  assert own.select.tau(fitted=True) == 0.0 and own.select.tau(fitted=False) == 0.002
  assert SelectConfig(prior_weight=0.05).tau(fitted=False) == 0.05  # None: prior_weight
  assert DecomposeConfig.from_eval(own.to_eval()) == own
  for bad in (-1.0, float("nan")):
    with pytest.raises(ValueError, match="select.network_prior_weight must be finite"):
      DecomposeConfig(select=SelectConfig(network_prior_weight=bad))


def test_the_screen_refuses_bad_settings_and_knows_when_it_is_off():
  assert sampling.check_screen(32, 64, 512, 256)
  assert not sampling.check_screen(0, 64, 512, 256)  # off
  assert not sampling.check_screen(256, 64, 512, 256)  # the prefix is the whole trajectory
  assert not sampling.check_screen(32, 512, 512, 256)  # everyone survives
  for steps, keep in ((-1, 8), (8, 0)):
    with pytest.raises(ValueError, match="screen_steps must be >= 0"):
      sampling.check_screen(steps, keep, 16, 256)


@pytest.mark.slow  # compiles the screen's short rollouts and the survivors' whole ones
def test_screened_selection_keeps_the_survivors_scores_and_the_winner(tower):
  """The screen simulates the survivors exactly as exhaustive selection does; with enough
  survivors it finds the same densities (the truth here)."""
  prims, observed = tower
  true = np.asarray(jnp.rint(prims.density / 100.0) - 1).astype(int)
  logits = jnp.full((5, 100), -1e9)
  for k in range(2):
    t = true[k]
    logits = logits.at[k, t - 3].set(0.0).at[k, t].set(0.5).at[k, t + 3].set(1.0)
  select = lambda **kw: jax.jit(lambda p, lg, o, key: sampling.select_densities(
      p, lg, o, PUSHES, num_samples=16, key=key, **kw))(prims, logits, observed,
                                                          jax.random.key(0))
  full, screened = select(), select(screen_steps=8, screen_keep=4)
  scores, kept = np.asarray(screened.scores), np.isfinite(np.asarray(screened.scores))
  assert kept.sum() == 4
  np.testing.assert_allclose(scores[kept], np.asarray(full.scores)[kept], rtol=1e-5)
  np.testing.assert_allclose(screened.density[:2], prims.density[:2])
  assert float(screened.score) == pytest.approx(float(full.score), abs=1e-7)


@pytest.mark.slow  # compiles sampling with a horizon (~110 s on 2 cores); the evaluation's
# replay of it is pinned by the rows' tests, decompose's by test_one_pipeline's slow tests
def test_selection_over_a_horizon_picks_the_candidate_closest_over_its_first_steps():
  """`selection_horizon`: the winner is the closest over the first steps, not over the
  whole trajectory; the scores returned stay whole-trajectory. The observation here is
  the tower's own first 8 steps followed by those of the tower at three times its
  densities, so the two rules pick different candidates."""
  prims = jax.tree.map(jnp.asarray, towers.sample_towers(3, 1, num_blocks=2))
  true = np.asarray(jnp.rint(prims.density[0] / 100.0) - 1).astype(int)
  early, late = _simulate(prims)[0], _simulate(prims.replace(density=prims.density * 3.0))[0]
  observed = jnp.concatenate([early[:, :8], late[:, 8:]], 1)
  prims = jax.tree.map(lambda x: x[0], prims)
  logits = jnp.full((5, 100), -1e9)
  for k in range(2):  # each box: its own slot or the one of three times its density
    logits = logits.at[k, true[k]].set(0.0).at[k, min(3 * true[k] + 2, 99)].set(0.0)
  sel = jax.jit(lambda p, lg, o, key: sampling.select_densities(
      p, lg, o, PUSHES, num_samples=8, key=key, selection_horizon=8))(prims, logits, observed,
                                                                     jax.random.key(0))
  prefix, _ = jax.jit(lambda b, o: sampling.score_candidates(b, o, PUSHES))(sel.boxes,
                                                                       observed[:, :8])
  assert int(sel.best) == int(np.argmin(prefix)) != int(np.argmin(sel.scores))
  np.testing.assert_allclose(sel.density[:2], prims.density[:2])
  assert float(sel.score) == pytest.approx(float(sel.scores[int(sel.best)]))
  for bad in (-1, 2.5):
    with pytest.raises(ValueError, match="selection_horizon must be a whole number"):
      sampling.select_densities(prims, logits, observed, PUSHES, num_samples=8,
                                key=jax.random.key(0), selection_horizon=bad)
    with pytest.raises(ValueError, match="selection_horizon must be a whole number"):
      DecomposeConfig().replace(**{"select.horizon": bad})


def test_the_refinement_horizon_doubles_then_covers_the_trajectory():
  h = refine.horizon_schedule(12, 8, 256)
  assert h.tolist() == [8, 8, 16, 32, 64, 128] + [256] * 7  # 12 iterations: 13 passes
  assert refine.horizon_schedule(4, 8, 16).tolist() == [8, 8, 16, 16, 16]
  assert refine.horizon_schedule(6, 300, 256).tolist() == [256] * 7  # nothing to warm up
  h = refine.horizon_schedule(24, 8, 256)
  assert np.all(np.diff(h) >= 0) and np.sum(h == 256) == 13 and h[0] == 8
  with pytest.raises(ValueError, match="each of the 3 passes"):
    one = jax.tree.map(lambda x: jnp.asarray(x[0]), towers.sample_towers(0, 1))
    refine.refine_densities(one, jnp.zeros((4, 16, 7)), steps=2, horizons=[8, 16])


def test_difference_jacobian_keeps_jacfwd_contract():
  """Forward differences: jacfwd's (..., K) layout, the aux at u, and the derivative of a
  smooth function to the step's order."""
  def residual(u):  # (3, 2) residuals of K = 3 parameters, and an aux
    r = jnp.stack([jnp.sin(u) * u[0], jnp.exp(0.1 * u) + u[2] ** 2], -1)
    return r, {"u": u, "r": r}
  u = jnp.array([0.3, -1.2, 0.7])
  want, aux_want = jax.jacfwd(residual, has_aux=True)(u)
  got, aux = refine.difference_jacobian(residual, u, 1e-3)
  assert got.shape == want.shape == (3, 2, 3)
  np.testing.assert_allclose(got, want, atol=5e-3)
  np.testing.assert_array_equal(aux["u"], aux_want["u"])  # the aux at u, not at a step
  central, aux = refine.difference_jacobian(residual, u, 1e-2, central=True)
  np.testing.assert_allclose(central, want, atol=1e-3)  # second order: a 10x step is fine
  np.testing.assert_array_equal(aux["u"], aux_want["u"])


def test_refinement_multiplies_in_full_float32(monkeypatch):
  """Every product of the LM iterations asks for full precision: GPUs otherwise multiply
  float32 in TF32, by the batch's shapes (docs/inference.md, Refinement). A stand-in
  simulator keeps the trace short; the real ones trace inside the same context."""
  def dots(jaxpr):
    for eqn in jaxpr.eqns:
      if eqn.primitive.name == "dot_general":
        yield str(eqn.params["precision"])
      for p in eqn.params.values():
        for sub in (p if isinstance(p, (list, tuple)) else [p]):
          if isinstance(sub, jax.extend.core.ClosedJaxpr):
            yield from dots(sub.jaxpr)
  def fake_simulate(prims, pushes, *, steps, settings):  # (P, T, 7), smooth in the densities
    del settings
    pos = (prims.density[:, None, None] * jnp.ones((steps, 3)) @ jnp.ones((3, 3))).sum(0) * 1e-6
    quat = jnp.broadcast_to(jnp.array([1.0, 0, 0, 0]), (steps, 4))
    return jnp.broadcast_to(jnp.concatenate([pos, quat], -1), (pushes.num, steps, 7))
  monkeypatch.setattr(refine, "simulate", fake_simulate)
  one = jax.tree.map(lambda x: jnp.asarray(x[0]), towers.sample_towers(0, 1))
  for jacobian in ("forward", "differences"):
    jaxpr = jax.make_jaxpr(lambda p, o, j=jacobian: refine.refine_densities(
        p, o, steps=2, horizons=[8, 16, 16], jacobian=j))(one, jnp.zeros((4, 16, 7)))
    found = list(dots(jaxpr.jaxpr))
    assert found and set(found) == {"(Precision.HIGHEST, Precision.HIGHEST)"}, set(found)


def smooth_simulate(prims, pushes, *, steps, settings, amplitude=1e-3, rate=0.05):
  """A stand-in engine, (P, T, 7): x reads each box's log density (`amplitude` metres per
  unit, oscillating at `rate` per step), y its inertia scale, both smoothly (one basin)."""
  del settings
  t = jnp.arange(steps)[:, None] * (jnp.arange(prims.valid.shape[0]) + 1.0)
  live = jnp.where(prims.valid, 1.0, 0.0)
  log_density = jnp.log(jnp.where(prims.valid, prims.density, 1e3) / 1e3)
  x = amplitude * (jnp.sin(rate * t) * log_density).sum(-1)
  scale = 1.0 if prims.inertia_scale is None else prims.inertia_scale
  y = 1e-2 * (jnp.cos(0.07 * t) * (scale - 1.0) * live).sum(-1)
  pose = jnp.concatenate([jnp.stack([x, y, 0 * x], -1), jnp.tile(jnp.array(
      [1.0, 0, 0, 0]), (steps, 1))], -1)
  return jnp.broadcast_to(pose, (pushes.num, steps, 7))


def test_refinement_fits_inertia_scales_within_their_range(monkeypatch):
  """With `inertia`, each valid box's inertia scale is an unknown beside its density: a
  stand-in simulator whose motion reads both (smoothly, as a hollow block's does) is
  matched where densities alone cannot match it, the scales stay within
  INERTIA_SCALE_RANGE, and boxes given without scales (the candidates') come back with them."""
  monkeypatch.setattr(refine, "simulate", smooth_simulate)
  truth = jax.tree.map(lambda x: jnp.asarray(x[0]), towers.sample_towers(1, 1, num_blocks=3))
  lo, hi = refine.INERTIA_SCALE_RANGE
  scale = jnp.where(truth.valid, jnp.array([1.4, 0.75, 2.3, 1.0, 1.0]), 1.0)  # 2.3: beyond
  observed = smooth_simulate(truth.replace(inertia_scale=scale), PUSHES, steps=32, settings=None)
  start = truth.replace(density=truth.density * 1.3)  # uniform boxes, 30 % heavy
  run = lambda inertia: jax.jit(lambda p, o: refine.refine_if_closer(
      p, o, jnp.float32(1.0), PUSHES, steps=8, inertia=inertia, jacobian="differences"))(
          start, observed)
  with_scales, densities_only = run(True), run(False)
  got = np.asarray(with_scales.primitives.inertia_scale)
  v = np.asarray(truth.valid)
  np.testing.assert_allclose(got[v], np.clip(np.asarray(scale)[v], lo, hi), rtol=0.03)
  np.testing.assert_allclose(np.asarray(with_scales.primitives.density)[v],
                             np.asarray(truth.density)[v], rtol=0.02)
  assert np.all(got[~v] == 1.0)
  assert densities_only.primitives.inertia_scale is None
  assert float(with_scales.cost) < 0.2 * float(densities_only.cost)


def test_refining_from_several_candidates_keeps_the_closest_refined(monkeypatch):
  """`refine_from_candidates`: one start is the closest distinct candidate refined as
  `refine_if_closer` refines it; several return the least distance of their refinements;
  a repeat is never a start; a score that is NaN (a rollout that blew up) never is one."""
  fake_simulate = functools.partial(smooth_simulate, amplitude=1e-2, rate=0.3)
  monkeypatch.setattr(refine, "simulate", fake_simulate)
  truth = jax.tree.map(lambda x: jnp.asarray(x[0]), towers.sample_towers(2, 1, num_blocks=3))
  observed = fake_simulate(truth, PUSHES, steps=24, settings=None)
  factors = jnp.asarray([1.3, 1.3, 0.6, 2.5])  # the second a repeat of the first
  boxes = jax.tree.map(lambda x: jnp.broadcast_to(x, (4,) + x.shape), truth).replace(
      density=truth.density * factors[:, None])
  scores = jax.vmap(lambda b: metrics.trajectory_distance(
      fake_simulate(b, PUSHES, steps=24, settings=None), observed))(boxes)
  distinct = jnp.asarray([True, False, True, True])
  options = {"steps": 3, "jacobian": "differences"}
  run = lambda starts, u=distinct: jax.jit(lambda b, s, o: refine.refine_from_candidates(
      b, s, u, o, PUSHES, starts=starts, **options))(boxes, scores, observed)
  alone = [jax.jit(lambda p, o: refine.refine_if_closer(p, o, scores.min(), PUSHES,
                                                        **options))(
               jax.tree.map(lambda x, i=i: x[i], boxes), observed) for i in (0, 2, 3)]
  one, three = run(1), run(3)
  assert float(one.distance) == pytest.approx(float(alone[0].distance), rel=1e-5)
  assert float(three.distance) == pytest.approx(min(float(r.distance) for r in alone),
                                                rel=1e-5)
  assert float(three.distance) <= float(one.distance) and bool(three.closer)
  # the closest flagged a repeat: the next distinct one starts
  moved = run(1, jnp.asarray([False, False, True, True]))
  assert float(moved.distance) == pytest.approx(float(alone[1].distance), rel=1e-5)
  blew_up = jax.jit(lambda b, s, o: refine.refine_from_candidates(
      b, s, distinct, o, PUSHES, starts=1, **options))(boxes, scores.at[0].set(jnp.nan),
                                                          observed)
  assert float(blew_up.distance) == pytest.approx(float(alone[1].distance), rel=1e-5)
  with pytest.raises(ValueError, match="without a prior"):
    refine.refine_from_candidates(boxes, scores, distinct, observed, PUSHES, starts=2,
                                  prior=(jnp.zeros(5), jnp.ones(5)), prior_weight=1e-5)


def test_refine_starts_are_checked_and_carried_by_the_eval_section():
  from ppdjax.configs.schema import ConfigError  # pylint: disable=import-outside-toplevel
  cfg = DecomposeConfig().replace(**{"refine.enabled": True, "refine.starts": 4})
  assert DecomposeConfig.from_eval(cfg.to_eval()) == cfg
  assert DecomposeConfig.from_eval(tiny.get_config().eval).refine.starts == 1
  for bad in (0, 1.5, True):
    with pytest.raises(ConfigError, match="refine.starts must be"):
      DecomposeConfig().replace(**{"refine.starts": bad})
  on = {"refine.enabled": True}
  with pytest.raises(ConfigError, match="refine.prior_weight 0"):
    DecomposeConfig().replace(**on, **{"refine.starts": 4, "refine.prior_weight": 1e-5})
  with pytest.raises(ConfigError, match="at most select.samples"):
    DecomposeConfig().replace(**on, **{"refine.starts": 9, "select.samples": 8})
  # unrefined settings carry the key without checking it (the appearance-only pass)
  assert DecomposeConfig().replace(**{"refine.starts": 9, "select.samples": 1}).refine.starts == 9


def test_refine_jacobian_names_the_choices():
  assert refine.check_jacobian("differences") == "differences"
  with pytest.raises(ValueError, match="jacobian must be one of"):
    refine.check_jacobian("reverse")
  with pytest.raises(ValueError, match="jacobian must be one of"):
    DecomposeConfig().replace(**{"refine.jacobian": "auto"})


@pytest.mark.slow  # four compilations through MJX: about two minutes on 2 cores
def test_difference_jacobian_through_physics_matches_forward_mode():
  """On a tower that moves (10-20 cm), forward differences of step 1e-3 in log density
  agree with forward mode over the first 32 steps (measured 0.3-0.6 % relative). On one
  that barely moves (0.2 mm: contacts switch) the two Jacobians differ, yet LM lands on the
  same densities with either (docs/inference.md)."""
  cheap = MjxSettings(iterations=1, ls_iterations=1, push_iterations=2, push_ls_iterations=1)
  from ppdjax.sim import rollout_mjx

  def case(prims):
    one = jax.tree.map(lambda x: x[0], jax.tree.map(jnp.asarray, prims))
    observed = rollout_mjx.simulate(one, PUSHES, steps=32, settings=cheap)
    return one, observed

  one, observed = case(towers.sample_towers(3, 1))

  def residual(u):
    sim = rollout_mjx.simulate(one.replace(density=jnp.exp(u)), PUSHES, steps=32,
                               settings=cheap)
    return metrics.pose_residual(sim, observed), sim
  u = jnp.log(one.density * 1.3)
  forward, _ = jax.jit(lambda u: jax.jacfwd(residual, has_aux=True)(u))(u)
  diff, _ = jax.jit(lambda u: refine.difference_jacobian(residual, u))(u)
  valid = np.asarray(one.valid)
  a, b = np.asarray(forward)[..., valid], np.asarray(diff)[..., valid]
  assert np.linalg.norm(a - b) < 0.02 * np.linalg.norm(a)

  one, observed = case(towers.sample_towers(11, 1, num_blocks=2))
  start = one.replace(density=one.density * jnp.array([1.3, 0.7, 1.0, 1.0, 1.0]))
  fits = {j: jax.jit(lambda p, o, j=j: refine.refine_densities(
      p, o, PUSHES, steps=6, jacobian=j, settings=cheap))(start, observed)
          for j in ("forward", "differences")}
  for _, info in fits.values():
    assert float(info["cost"]) < 0.5 * float(info["cost_start"])
  np.testing.assert_allclose(fits["differences"][0].density, fits["forward"][0].density,
                             rtol=0.01)


@pytest.mark.slow  # two compilations of the refinement: about 2 minutes on 2 cores
def test_per_object_map_weights_match_one_weight_at_a_time():
  """`refine_batch` with (B,) weights (one compiled call for a sweep, prior_study.py) gives
  each object what a call with its weight alone gives; a heavy weight pulls to the prior."""
  prims = jax.tree.map(lambda x: jnp.asarray(x[:2]), towers.sample_towers(11, 2, num_blocks=2))
  observed = _simulate(prims)[:, :, :32]
  start = prims.replace(density=prims.density * 1.3)
  logits = jnp.zeros(prims.density.shape + (100,))
  d0, m0 = jnp.full((2,), jnp.inf), jnp.zeros((2,))
  mags = jnp.broadcast_to(PUSHES.magnitudes, (2, PUSHES.num))
  kw = dict(steps=3, pushes=PUSHES, settings=DEFAULT_SETTINGS)
  both = refine.refine_batch(start, logits, observed, d0, m0, mags,
                             prior_weight=jnp.asarray([1e-5, 1e3]), **kw)
  one = refine.refine_batch(start, logits, observed, d0, m0, mags, prior_weight=1e-5, **kw)
  np.testing.assert_allclose(both["density"][0], one["density"][0], rtol=1e-5)
  mean, _ = refine.density_prior(logits[1])
  gap = lambda d: np.abs(np.log(np.asarray(d)[:2]) - np.asarray(mean)[:2])  # the two blocks
  assert np.all(gap(both["density"][1]) < gap(start.density[1]))


@pytest.mark.slow
def test_refinement_from_thirty_percent_off_lands_within_five_percent():
  prims = jax.tree.map(jnp.asarray, towers.sample_towers(11, 24, num_blocks=2))
  observed = _simulate(prims)
  moved = jnp.linalg.norm(observed[..., :3] - observed[:, :, :1, :3], axis=-1).mean((1, 2))
  # towers whose motion shows how their mass is split (docs/inference.md: identifiability)
  pick = np.nonzero(np.asarray(moved) > 0.05)[0][:6]
  assert len(pick) >= 4
  prims, observed = jax.tree.map(lambda x: x[pick], prims), observed[pick]
  signs = jnp.asarray(np.random.default_rng(0).choice([-1.0, 1.0], (len(pick), 5)))
  start = prims.replace(density=prims.density * (1.0 + 0.3 * signs))
  out, info = jax.jit(jax.vmap(lambda p, o: refine.refine_densities(p, o, PUSHES)))(
      start, observed)
  ratio = np.asarray(out.density / prims.density)[:, :2]
  assert np.all(np.abs(ratio - 1.0) < 0.05), ratio
  assert np.all(np.asarray(info["cost"]) < np.asarray(info["cost_start"]))


@pytest.fixture(scope="module")
def decompose(tiny_run):
  """decompose with refinement, compiled once for these tests (the demo's smoke run tests
  it without). Fewer solver iterations than the dataset's halve the compile time on a CPU;
  the code path is the default one. The fit (on by default) is left out here: the shipped
  example's test (test_demo.py) decomposes with it."""
  cheap = MjxSettings(iterations=1, ls_iterations=1, push_iterations=2, push_ls_iterations=1)
  config = DecomposeConfig(fit=FitConfig(enabled=False), select=SelectConfig(samples=SAMPLES),
                           refine=RefineConfig(enabled=True, steps=2))
  return ppdjax.make_decompose_fn(tiny_run[0], config, engine=cheap)


@pytest.mark.slow  # compiling decompose with refinement: about a minute on 2 cores
def test_decompose_one_and_a_batch_with_refinement(decompose, tiny_dataset):
  """One object and a batch of one agree; refinement (LM through MJX, in the same jit) is
  kept only where it is closer, so the answer is never further than the best sample."""
  sample = storage.open_dataset(tiny_dataset, "test").take([0])
  obs = {k: sample[k] for k in OBS_KEYS}
  batched = decompose(obs, jax.random.key(0))
  one = decompose(jax.tree.map(lambda x: x[0], obs), jax.random.key(0))
  assert batched.primitives.density.shape == (1, 5) and one.primitives.density.shape == (5,)
  np.testing.assert_allclose(one.primitives.density, batched.primitives.density[0])
  assert one.scores.shape == (SAMPLES,) and float(one.score) <= float(one.scores.min()) + 1e-7
  d = np.asarray(one.primitives.density)[np.asarray(one.primitives.valid)]
  assert np.all((d >= 100) & (d <= 10000))
  if float(one.score) >= float(one.scores.min()):  # refinement not kept: a sampled slot
    np.testing.assert_allclose(d % 100, 0, atol=1e-3)
  np.testing.assert_allclose(metrics.trajectory_distance(one.trajectories,
                                                         obs["trajectories"][0]), one.score,
                             rtol=1e-4)
  # the candidates and each box's posterior over them (tests/test_posterior.py)
  valid = np.asarray(one.primitives.valid)
  assert one.candidates.shape == (SAMPLES, 5) and one.posterior.probs.shape == (5, 100)
  np.testing.assert_array_equal(np.asarray(one.candidates[0])[valid],
                                np.asarray(one.density_logits).argmax(-1)[valid])
  np.testing.assert_allclose(np.asarray(one.posterior.probs).sum(-1), valid, atol=1e-5)
  assert np.all(np.asarray(one.posterior.lower) <= np.asarray(one.posterior.upper))


@pytest.mark.slow  # compiling decompose with +Search and refinement: about 3 minutes
def test_decompose_with_search_returns_every_round_and_boxes_with_inertia(tiny_run,
                                                                          tiny_dataset):
  """+Search in decompose (two rounds, inertia scales): every round's candidates reach the
  answer's scores, candidates and posterior; the answer's boxes carry a scale of
  search.INERTIA_LEVELS (refinement keeps the winner's, `refine.inertia` off) and it is
  never further than the closest candidate."""
  cheap = MjxSettings(iterations=1, ls_iterations=1, push_iterations=2, push_ls_iterations=1)
  config = DecomposeConfig(fit=FitConfig(enabled=False),
                           select=SelectConfig(samples=SAMPLES, rounds=2, inertia=True),
                           refine=RefineConfig(enabled=True, steps=1))
  fn = ppdjax.make_decompose_fn(tiny_run[0], config, engine=cheap)
  sample = storage.open_dataset(tiny_dataset, "test")[0]
  one = fn({k: sample[k] for k in OBS_KEYS}, jax.random.key(0))
  valid = np.asarray(one.primitives.valid)
  assert one.scores.shape == (2 * SAMPLES,) and one.candidates.shape == (2 * SAMPLES, 5)
  assert np.all(np.isfinite(np.asarray(one.scores)))
  assert float(one.score) <= float(one.scores.min()) + 1e-7
  scale = np.asarray(one.primitives.inertia_scale)
  levels = np.asarray(search.INERTIA_LEVELS)
  assert np.all(np.abs(scale[valid][:, None] - levels).min(-1) < 1e-5), scale
  np.testing.assert_allclose(np.asarray(one.posterior.probs).sum(-1), valid, atol=1e-5)


@pytest.mark.slow  # the decompose fixture's compile, then 4 hypotheses x 64 pushes
def test_next_push_scores_the_candidate_pushes_for_one_object_and_a_batch(decompose,
                                                                          tiny_dataset):
  """`make_next_push_fn` beside a decompose: every candidate push gets a finite gain in
  [0, log hypotheses] nats, the best is the largest, one object and a batch of one agree."""
  sample = storage.open_dataset(tiny_dataset, "test").take([0])
  obs = {k: sample[k] for k in OBS_KEYS}
  batched = decompose(obs, jax.random.key(0))
  next_push = ppdjax.make_next_push_fn(decompose, hypotheses=4)
  assert next_push.candidates.num == 64
  many, one = next_push(batched), next_push(jax.tree.map(lambda x: x[0], batched))
  gain = np.asarray(one.gain)
  assert gain.shape == (64,) and many.gain.shape == (1, 64)
  assert np.all(np.isfinite(gain)) and gain.min() >= -1e-6 and gain.max() <= np.log(4) + 1e-3
  assert int(one.best) == int(gain.argmax())
  np.testing.assert_allclose(gain, np.asarray(many.gain[0]), rtol=1e-5, atol=1e-6)
  with pytest.raises(ValueError, match="hypotheses must be a whole number >= 2"):
    ppdjax.make_next_push_fn(decompose, hypotheses=1)


def test_bad_observations_are_named(decompose, tiny_dataset):
  sample = storage.open_dataset(tiny_dataset, "test")[0]
  obs = {k: sample[k] for k in OBS_KEYS}
  key = jax.random.key(0)
  with pytest.raises(ValueError, match="lacks"):
    decompose({"voxels": obs["voxels"]}, key)
  with pytest.raises(ValueError, match=r"trajectories.*expected shape \(4, any, 7\)"):
    decompose({**obs, "trajectories": obs["trajectories"][:, :, :3]}, key)
  with pytest.raises(ValueError, match="voxels"):
    decompose({**obs, "voxels": obs["voxels"][:16]}, key)
  with pytest.raises(ValueError, match="NaN or inf"):
    decompose({**obs, "trajectories": obs["trajectories"].copy() * np.nan}, key)
  with pytest.raises(ValueError, match="image.*uint8"):  # a float image in [0, 1]
    decompose({**obs, "image": obs["image"] / 255.0}, key)
  with pytest.raises(ValueError, match="voxels.*0/1"):
    decompose({**obs, "voxels": obs["voxels"] * 255}, key)
  with pytest.raises(ValueError, match=r"push_magnitudes.*expected shape \(4,\)"):
    decompose({**obs, "push_magnitudes": np.ones(3, np.float32)}, key)
  with pytest.raises(ValueError, match="push_magnitudes.*finite"):
    decompose({**obs, "push_magnitudes": np.full(4, np.nan, np.float32)}, key)


def test_the_depth_fit_in_decompose_names_its_errors(tiny_run, tiny_dataset):
  """A camera needs the fit and a depth image of its size, finite and positive; all is
  checked before anything compiles."""
  ds = storage.open_dataset(tiny_dataset, "test")
  sample = ds[0]
  obs = {k: sample[k] for k in OBS_KEYS}
  two = DecomposeConfig(select=SelectConfig(samples=2))
  with pytest.raises(ValueError, match="this config reads neither"):
    ppdjax.make_decompose_fn(tiny_run[0], two, camera=ds.camera)
  with pytest.raises(ValueError, match="need fit.enabled"):
    two.replace(**{"fit.enabled": False, "fit.face_spread": 0.5})
  with pytest.raises(ValueError, match=r"face_spread must be in \[0, 0.5\]"):
    two.replace(**{"fit.face_spread": 1.0})
  with pytest.raises(ValueError, match="camera"):
    ppdjax.make_decompose_fn(tiny_run[0], two.replace(**{"fit.image": True}),
                             camera={"height": 8})
  with pytest.raises(TypeError, match="expected a DecomposeConfig"):
    ppdjax.make_decompose_fn(tiny_run[0], {"fit": "image"})
  # without a camera, the model's own: its training data's
  by_image = ppdjax.make_decompose_fn(tiny_run[0], two.replace(**{"fit.image": True}))
  with pytest.raises(ValueError, match="image: expected shape"):
    by_image({**obs, "image": sample["image"][:-1]}, jax.random.key(0))
  decompose = ppdjax.make_decompose_fn(tiny_run[0], two.replace(**{"fit.depth": True}),
                                       camera=ds.camera)
  key = jax.random.key(0)
  with pytest.raises(ValueError, match="lacks 'depth'"):
    decompose(obs, key)
  with pytest.raises(ValueError, match="depth image is 63x64"):
    decompose({**obs, "depth": sample["depth"][:-1]}, key)
  with pytest.raises(ValueError, match="finite and > 0"):
    decompose({**obs, "depth": sample["depth"] * np.nan}, key)


def test_density_prior_is_the_moments_of_the_networks_scores():
  from ppdjax.infer.refine import density_prior
  logits = jnp.full((2, 100), -1e9).at[0, 9].set(0.0).at[1, 9].set(0.0).at[1, 39].set(0.0)
  mean, std = density_prior(logits)
  np.testing.assert_allclose(mean[0], np.log(1000.0), rtol=1e-6)
  assert float(std[0]) == pytest.approx(0.05)  # a point mass gets the floor
  np.testing.assert_allclose(mean[1], (np.log(1000.0) + np.log(4000.0)) / 2, rtol=1e-6)
  np.testing.assert_allclose(std[1], (np.log(4000.0) - np.log(1000.0)) / 2, rtol=1e-5)


def test_bootstrap_interval_covers_a_proportion():
  hits = np.r_[np.ones(30), np.zeros(70)]
  lo, hi = metrics.bootstrap_interval(lambda i: 100.0 * hits[i].mean(), len(hits))
  assert 19 < lo < 30 < hi < 41  # binomial 95 % interval of 30 % of 100 is about ±9
  assert metrics.bootstrap_interval(lambda i: 1.0, 5) == (1.0, 1.0)
  with pytest.raises(ValueError, match="at least one object"):
    metrics.bootstrap_interval(lambda i: 0.0, 0)


def test_bootstrap_over_groups_widens_for_shared_outcomes():
  """A tower's or tool's configurations share its shape: a cluster bootstrap draws them
  together. Outcomes that a group shares give a wider interval than objects drawn one by
  one; groups of one object each draw exactly what the object bootstrap draws."""
  rng = np.random.default_rng(0)
  group = np.repeat(np.arange(100), 8)  # 100 tools x 8 configurations
  hits = np.repeat(rng.random(100) < 0.3, 8).astype(float)  # one outcome a tool
  stat = lambda i: 100.0 * hits[i].mean()  # noqa: E731
  lo, hi = metrics.bootstrap_interval(stat, len(hits))
  glo, ghi = metrics.bootstrap_interval(stat, len(hits), groups=group)
  assert glo < lo and ghi > hi and (ghi - glo) > 2 * (hi - lo)  # about sqrt(8) wider
  v = rng.random(40)
  mean = lambda i: float(v[i].mean())  # noqa: E731
  assert (metrics.bootstrap_interval(mean, 40, groups=np.arange(40))
          == metrics.bootstrap_interval(mean, 40))
  uneven = rng.integers(0, 7, 40)  # groups of any sizes, ids in any order
  lo, hi = metrics.bootstrap_interval(mean, 40, groups=uneven * 10 + 3)
  assert lo < mean(np.arange(40)) < hi
  with pytest.raises(ValueError, match="one id per object"):
    metrics.bootstrap_interval(mean, 40, groups=np.arange(39))


def test_scale_to_mass_keeps_the_split_and_matches_the_total():
  """Mass-matched selection's rescaling: valid boxes scaled by one factor to the target
  total mass, padded boxes untouched, densities kept in the slot range."""
  prims = ppdjax.Primitives(
      half_size=jnp.full((2, 3, 3), 0.05), pos=jnp.zeros((2, 3, 3)),
      quat=jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (2, 3, 1)),
      density=jnp.asarray([[1000.0, 3000.0, 100.0], [500.0, 9000.0, 100.0]]),
      valid=jnp.asarray([[True, True, False], [True, True, False]]))
  target = 2.0 * sampling.total_mass(prims)
  out = sampling.scale_to_mass(prims, target)
  np.testing.assert_allclose(out.density[0], [2000.0, 6000.0, 100.0], rtol=1e-6)
  assert float(out.density[1, 1]) == 10000.0  # clipped at the slot range's top
  np.testing.assert_allclose(sampling.total_mass(out)[0], target[0], rtol=1e-6)
