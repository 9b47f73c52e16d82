"""Rollouts: MuJoCo C backend vs a plain mj_step loop, MJX and the box-plane step vs C, pushes,
rest state, derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import primitives
from ppdjax.conventions import TIMESTEP
from ppdjax.dataset import towers
from ppdjax.sim import box_plane_kernel, rollout_mjx, scene
from ppdjax.sim.box_plane import BoxPlaneSettings
from ppdjax.sim.pushes import default_pushes, push_points
from conftest import index
from mujoco_reference import reference_rollout

NUM_TOWERS = 16  # every box count among them (checked below)
DT = TIMESTEP


@pytest.fixture(scope="module")
def prims():
  batch = towers.sample_towers(7, NUM_TOWERS)
  assert set(np.asarray(batch.valid).sum(-1)) == {2, 3, 4, 5}  # every box count is covered
  return batch


@pytest.fixture(scope="module")
def c_traj(prims):
  return ppdjax.simulate(prims, backend="mujoco")


@pytest.fixture(scope="module")
def mjx_traj(prims):
  return np.asarray(ppdjax.simulate(prims, backend="mjx"))


def _gap_mm(a, b):
  return np.linalg.norm(np.asarray(a)[..., :3] - np.asarray(b)[..., :3], axis=-1) * 1e3


def test_mujoco_backend_matches_plain_mj_step_loop(prims, c_traj):
  pushes = ppdjax.default_pushes()
  for i in (0, 5, 11):
    ref = reference_rollout(index(prims, i), pushes)  # a model MuJoCo compiled from the boxes
    assert _gap_mm(c_traj[i], ref).max() < 0.5


def test_mjx_matches_c_engine(c_traj, mjx_traj):
  assert mjx_traj.shape == (NUM_TOWERS, 4, 256, 7) and mjx_traj.dtype == np.float32
  gap = _gap_mm(mjx_traj, c_traj).reshape(-1, 256)
  early = gap[:, :30].max(-1)  # the first 0.1 s, before boxes land
  final = gap[:, -1]
  print(f"\nMJX vs C over {gap.shape[0]} rollouts: first 0.1 s p50/p90/max "
        f"{np.percentile(early, 50):.3f}/{np.percentile(early, 90):.3f}/{early.max():.3f} mm; "
        f"all steps median {np.median(gap):.3f} mm; after 256 steps p50/p90/max "
        f"{np.percentile(final, 50):.2f}/{np.percentile(final, 90):.1f}/{final.max():.1f} mm")
  assert np.percentile(early, 90) < 2.0
  assert np.median(gap) < 1.0


def test_rest_state_is_one_micron_into_the_ground(prims, c_traj, mjx_traj):
  rest = np.asarray(scene.rest_position(jax.tree.map(jnp.asarray, prims)))
  lowest = rest[:, 2] + np.asarray(primitives.lowest_point(jax.tree.map(jnp.asarray, prims)))
  np.testing.assert_allclose(lowest, -1e-6, atol=1e-7)
  # Regression guard: at exactly z = 0 float32 MJX loses the resting contacts during the
  # push and drives the object millimetres into the floor within the first steps.
  assert _gap_mm(mjx_traj[..., :5, :], c_traj[..., :5, :]).max() < 0.1


def test_push_impulse(prims):
  """A steep lifting push through the centre of mass: horizontal momentum after the push
  step equals F_h dt (within 5%), in both engines.

  The paper's pushes act off the centre of mass, so they also tip the object: its lower
  edge is driven into the ground and the ground's impulsive friction takes a share of
  the horizontal momentum (in MuJoCo C as in MJX; docs/physics.md gives the numbers).
  """
  direction = np.float32([[0.3, 0.3, 1], [-0.3, 0.3, 1], [0.3, -0.3, 1], [-0.3, -0.3, 1]])
  direction /= np.linalg.norm(direction, axis=1, keepdims=True)
  for i in (0, 6, 12):
    one = index(prims, i)
    com = np.asarray(ppdjax.mass_properties(jax.tree.map(jnp.asarray, one)).com)
    pushes = ppdjax.Pushes(com - 2 * direction, np.tile(com, (4, 1)),
                            np.full(4, 1e5, np.float32))
    for backend in ("mjx", "mujoco"):
      # the whole batch: the program mjx_traj compiles (pushes are inputs)
      first = np.asarray(ppdjax.simulate(prims, pushes, backend=backend))[i, :, 0]
      rest = np.asarray(scene.rest_position(jax.tree.map(jnp.asarray, one)))
      mass = float(ppdjax.mass_properties(jax.tree.map(jnp.asarray, one)).mass)
      momentum = mass * (first[:, :3] - rest) / DT  # no torque: pure translation
      expected = 1e5 * direction * DT
      rel = np.linalg.norm(momentum[:, :2] - expected[:, :2], axis=-1) / np.linalg.norm(
          expected[:, :2], axis=-1)
      assert rel.max() < 0.05, (i, backend, rel)
      np.testing.assert_allclose(first[:, 3:], np.tile([1.0, 0, 0, 0], (4, 1)), atol=1e-4)


def test_push_points_lie_on_the_surface(prims):
  pushes = ppdjax.default_pushes()
  for i in range(4):
    one = jax.tree.map(jnp.asarray, index(prims, i))
    pts = np.asarray(push_points(one, pushes))
    rot = np.asarray(primitives.quat_to_mat(one.quat))
    local = np.einsum("kji,pkj->pki", rot, pts[:, None] - np.asarray(one.pos)[None])
    excess = np.abs(local) - np.asarray(one.half_size)[None]
    on_box = np.abs(excess.max(-1)) < 1e-5  # on the surface of that box
    assert np.all((on_box & np.asarray(one.valid)[None]).any(-1))


def test_ray_that_misses_pushes_at_the_target():
  far = primitives.make([[0.05, 0.05, 0.05], [0.05, 0.05, 0.05]], [[0.4, 0.4, -0.4],
                                                                    [0.4, 0.4, -0.3]])
  pushes = ppdjax.Pushes(np.float32([[0, -1, 0]]), np.zeros((1, 3), np.float32),
                          np.float32([1e5]))
  pts = push_points(jax.tree.map(jnp.asarray, far), pushes)
  np.testing.assert_allclose(pts, 0.0)


def test_one_compiled_function_ignores_padding(prims, mjx_traj):
  """Garbage in invalid slots changes nothing; the same compiled function is reused."""
  from ppdjax.sim import rollout_mjx
  valid = np.asarray(prims.valid)
  garbage = prims.replace(
      half_size=np.where(valid[..., None], prims.half_size, np.float32(0.45)),
      pos=np.where(valid[..., None], prims.pos, np.float32(-0.4)),
      density=np.where(valid, prims.density, np.float32(9999.0)))
  fn = rollout_mjx._batched_fn(256, rollout_mjx.DEFAULT_SETTINGS)  # pylint: disable=protected-access
  before = fn._cache_size()  # pylint: disable=protected-access
  out = np.asarray(ppdjax.simulate(garbage, backend="mjx"))
  assert fn._cache_size() == before  # pylint: disable=protected-access
  np.testing.assert_allclose(out, mjx_traj, atol=1e-5)


def test_leading_batch_axes(prims, mjx_traj):
  grid = jax.tree.map(lambda x: np.reshape(x, (2, NUM_TOWERS // 2) + np.shape(x)[1:]), prims)
  out = ppdjax.simulate(grid)
  assert out.shape == (2, NUM_TOWERS // 2, 4, 256, 7)
  np.testing.assert_allclose(np.reshape(out, mjx_traj.shape), mjx_traj, atol=1e-6)


@pytest.mark.slow  # ~25 s to compile; sampling and refinement trace simulate under jit too
def test_simulate_under_jit_with_fewer_steps(prims, mjx_traj):
  short = jax.jit(lambda p: ppdjax.simulate(p, steps=8))(jax.tree.map(jnp.asarray,
                                                                       index(prims, 0)))
  np.testing.assert_allclose(short, mjx_traj[0, :, :8], atol=1e-5)


@pytest.mark.slow  # a cross-check of ~60 s; decompose(refine=True) runs jacfwd by default
@pytest.mark.parametrize("backend", ["mjx", "box_plane"])
def test_forward_mode_density_derivatives_vs_finite_differences(prims, backend):
  """d(trajectory)/d(log density) by jacfwd through each JAX engine against central
  differences.

  They agree while the contact set stays the same (the push and the first 1/30 s, through
  the push step's contacts). A contact that starts or ends (a box landing, an edge
  lifting) is a jump in the dynamics: the derivative then describes the nearby smooth
  branch and finite differences straddle the jump; the gap is printed, not asserted
  (docs/physics.md gives measured cases).
  """
  one = jax.tree.map(jnp.asarray, index(prims, 3))
  steps, h = 30, 1e-2

  def traj(log_density):
    return ppdjax.simulate(one.replace(density=jnp.exp(log_density)), steps=steps,
                           backend=backend)[..., :3]

  log_d = jnp.log(jnp.where(one.valid, one.density, 1.0))
  jac = np.asarray(jax.jacfwd(traj)(log_d))  # (P, steps, 3, K)
  fd = np.stack([(np.asarray(traj(log_d.at[k].add(h))) - np.asarray(traj(log_d.at[k].add(-h))))
                 / (2 * h) for k in range(5)], -1)
  valid = np.asarray(one.valid)
  assert np.all(np.isfinite(jac)) and np.all(jac[..., ~valid] == 0)
  scale = np.abs(fd[..., valid]).max(axis=(1, 2, 3))  # per push
  err = np.abs(jac - fd)[..., valid].max(axis=(2, 3)) / scale[:, None]  # (P, steps)
  print("\njacfwd vs FD, relative error per push over the first 10 / all 30 steps:",
        err[:, :10].max(1).round(4), err.max(1).round(3))
  assert err[:, :10].max() < 0.02


@pytest.mark.slow  # a cross-check of ~50 s on 2 cores: `make test-all`
def test_fixed_iteration_step_matches_mjx_step(prims):
  """ppdjax.sim.mjx_step (no while_loop, unrolled Cholesky) computes what mjx.step computes."""
  from ppdjax.sim.rollout_mjx import MjxSettings
  few = jax.tree.map(lambda x: x[:2], prims)
  ours = np.asarray(ppdjax.simulate(few, steps=30, settings=MjxSettings()))
  theirs = np.asarray(ppdjax.simulate(few, steps=30, settings=MjxSettings(
      fixed_iterations=False, unrolled_cholesky=False)))
  assert _gap_mm(ours, theirs).max() < 1e-3


@pytest.mark.parametrize("kwargs,message", [
    (dict(backend="bullet"), "backend must be one of"),
    (dict(steps=0), "steps must be a positive int"),
    (dict(pushes=ppdjax.Pushes(np.zeros((4, 2)), np.zeros((4, 3)), np.ones(4))),
     r"Pushes.sources: expected shape \(P, 3\)"),
    (dict(pushes=ppdjax.Pushes(np.ones((1, 3)), np.zeros((1, 3)), np.float32([np.nan]))),
     "Pushes.magnitudes: contains NaN"),
    (dict(pushes=ppdjax.Pushes(np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1))),
     "coincides with its target"),
    (dict(pushes=ppdjax.Pushes(np.ones((1, 3)), np.zeros((1, 3)), np.ones(1), duration=0)),
     "Pushes.duration"),
])
def test_bad_simulate_arguments(prims, kwargs, message):
  with pytest.raises(ValueError, match=message):
    ppdjax.simulate(index(prims, 0), **kwargs)


def test_bad_primitives_raise_before_simulating(prims):
  bad = index(prims, 0)
  bad = bad.replace(pos=np.asarray(bad.pos).copy())
  bad.pos[0, 0] = np.nan
  with pytest.raises(ValueError, match="Primitives.pos: contains NaN"):
    ppdjax.simulate(bad)
  with pytest.raises(ValueError, match="cannot be traced"):
    jax.jit(lambda p: ppdjax.simulate(p, backend="mujoco"))(
        jax.tree.map(jnp.asarray, index(prims, 0)))


@pytest.mark.slow
def test_reverse_mode_matches_forward_mode(prims):
  """jax.grad through the fixed-iteration step (no while_loop) equals jax.jacfwd."""
  one = jax.tree.map(jnp.asarray, index(prims, 3))
  log_d = jnp.log(jnp.where(one.valid, one.density, 1.0))

  def loss(ld):
    return ppdjax.simulate(one.replace(density=jnp.exp(ld)), steps=10)[..., :3].sum()

  grad = np.asarray(jax.grad(loss)(log_d))
  assert np.all(np.isfinite(grad))
  np.testing.assert_allclose(grad, jax.jacfwd(loss)(log_d), rtol=1e-3, atol=1e-6)


# The box-plane step (ppdjax.sim.box_plane): MuJoCo's contact model written for this scene.

@pytest.fixture(scope="module")
def box_plane_traj(prims):
  return np.asarray(ppdjax.simulate(prims, backend="box_plane"))


@pytest.mark.slow  # the box-plane step's XLA form compiles for 90 s on a CPU (decompose runs it on a GPU): `make test-all`
def test_box_plane_step_matches_c_engine_at_least_as_well_as_mjx(c_traj, mjx_traj,
                                                                   box_plane_traj):
  assert box_plane_traj.shape == (NUM_TOWERS, 4, 256, 7)
  assert box_plane_traj.dtype == np.float32
  stats = {}
  for name, traj in (("MJX", mjx_traj), ("box-plane", box_plane_traj)):
    gap = _gap_mm(traj, c_traj).reshape(-1, 256)
    early = gap[:, :30].max(-1)
    stats[name] = (np.percentile(early, 90), np.median(gap), np.percentile(gap[:, -1], 90))
    print(f"\n{name} vs C: first 0.1 s p90 {stats[name][0]:.3f} mm, all steps median "
          f"{stats[name][1]:.4f} mm, after 256 steps p90 {stats[name][2]:.1f} mm")
  early_p90, median, _ = stats["box-plane"]
  assert early_p90 < 2.0 and median < 1.0  # the fidelity bounds
  # at least as faithful as MJX (a float32 margin of 0.01 mm)
  assert early_p90 <= stats["MJX"][0] + 0.01 and median <= stats["MJX"][1] + 0.01


@pytest.mark.slow  # the box-plane step's XLA form compiles for 90 s on a CPU (decompose runs it on a GPU): `make test-all`
def test_box_plane_step_matches_mjx_before_landing(mjx_traj, box_plane_traj):
  """The same contact model: MJX and the box-plane step agree while the contact set is the
  resting one (after boxes land on edges, MJX's convex-mesh contacts differ from C's)."""
  early = _gap_mm(box_plane_traj[..., :30, :], mjx_traj[..., :30, :]).reshape(-1, 30).max(-1)
  assert np.percentile(early, 90) < 0.1


@pytest.mark.slow  # the box-plane step's XLA form compiles for 90 s on a CPU (decompose runs it on a GPU): `make test-all`
def test_box_plane_step_ignores_padding(prims, box_plane_traj):
  junk = jax.tree.map(np.array, prims)
  invalid = ~np.asarray(junk.valid)
  junk.half_size[invalid] = 0.3
  junk.pos[invalid] = -0.2
  junk.density[invalid] = 5e3
  out = np.asarray(ppdjax.simulate(junk, backend="box_plane"))  # same shapes: no recompile
  np.testing.assert_array_equal(out, box_plane_traj)


def test_box_plane_constants_are_the_scene_models():
  from ppdjax.sim import box_plane, newton
  model = scene.template_model()
  np.testing.assert_allclose(model.opt.gravity, box_plane.GRAVITY)
  assert model.opt.impratio == 1.0 and model.opt.timestep == TIMESTEP
  assert (model.opt.tolerance, model.opt.ls_tolerance) == (newton.TOLERANCE,
                                                           newton.LS_TOLERANCE)
  np.testing.assert_allclose(model.geom_friction[:, 0], box_plane.FRICTION)
  np.testing.assert_allclose(model.geom_solref, np.tile(box_plane.SOLREF, (model.ngeom, 1)))
  np.testing.assert_allclose(model.geom_solimp, np.tile(box_plane.SOLIMP, (model.ngeom, 1)))
  assert set(model.geom_condim) == {3} and model.opt.cone == 0  # pyramidal
  assert not model.geom_margin.any() and not model.geom_gap.any()


def test_box_plane_backend_takes_its_own_settings(prims):
  from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS, MjxSettings, settings_for
  assert settings_for("box_plane") == BoxPlaneSettings()  # evaluation reads the data's engine
  assert settings_for("mjx") == settings_for("mujoco") == DEFAULT_SETTINGS
  with pytest.raises(ValueError, match="box_plane.*BoxPlaneSettings"):
    ppdjax.simulate(index(prims, 0), backend="box_plane", settings=MjxSettings())
  with pytest.raises(ValueError, match="mjx.*MjxSettings"):
    ppdjax.simulate(index(prims, 0), backend="mjx", settings=BoxPlaneSettings())


@pytest.mark.slow  # interpreted on the CPU: about 30 s on 2 cores; `make test-all`
def test_box_plane_kernel_is_the_reference_step(prims, box_plane_traj):
  """The Pallas kernel (interpreted on the CPU; on a GPU it is one launch) runs the same
  physics as box_plane's step: every rollout of the nested vmaps in one call."""
  kernel = BoxPlaneSettings(kernel="pallas")
  four = jax.tree.map(lambda x: x[:4], prims)  # interpreting is slow: 16 rollouts, 48 steps
  out = np.asarray(ppdjax.simulate(four, steps=48, backend="box_plane", settings=kernel))
  assert out.shape == (4, 4, 48, 7) and out.dtype == np.float32
  gap = _gap_mm(out, box_plane_traj[:4, :, :48])
  assert gap.max() < 0.001, gap.max()
  # another launch shape (4 programs of 4 rollouts) runs the same physics
  small = BoxPlaneSettings(kernel="pallas", kernel_block=4, kernel_warps=1)
  out_small = np.asarray(ppdjax.simulate(four, steps=8, backend="box_plane", settings=small))
  assert _gap_mm(out_small, out[:, :, :8]).max() < 0.001
  with pytest.raises(ValueError, match="kernel must be one of"):
    BoxPlaneSettings(kernel="triton")
  with pytest.raises(ValueError, match="kernel_block must be 0 or a power of two"):
    BoxPlaneSettings(kernel_block=24)


def test_box_plane_kernel_launch_follows_the_batch():
  """Small launches (one object's candidates) take small programs, large ones (an
  evaluation's 65,536 rollouts) large ones; settings override either number."""
  default = BoxPlaneSettings()
  assert box_plane_kernel.launch_shape(default, 2048) == box_plane_kernel.SMALL_LAUNCH
  assert box_plane_kernel.launch_shape(default, 65536) == box_plane_kernel.LARGE_LAUNCH
  assert box_plane_kernel.launch_shape(BoxPlaneSettings(kernel_block=64), 65536) == (
      64, box_plane_kernel.LARGE_LAUNCH[1])


@pytest.mark.slow
def test_box_plane_kernel_with_all_contacts_is_the_reference_step(prims):
  """max_contacts=0 (every candidate in the solve, as MuJoCo C) against the reference."""
  four = jax.tree.map(lambda x: x[:4], prims)
  out = [np.asarray(ppdjax.simulate(four, steps=48, backend="box_plane", settings=BoxPlaneSettings(
      max_contacts=0, kernel=kernel))) for kernel in ("reference", "pallas")]
  assert _gap_mm(out[1], out[0]).max() < 0.001


@pytest.mark.slow
def test_box_plane_kernel_derivatives_are_the_reference_steps(prims):
  """jax.jvp through the kernel runs the reference step (custom_jvp): the same numbers."""
  one = jax.tree.map(lambda x: jnp.asarray(x[0]), prims)
  pushes = ppdjax.default_pushes()

  def traj(density, kernel):
    return rollout_mjx.simulate(one.replace(density=density), pushes, steps=24,
                                settings=BoxPlaneSettings(kernel=kernel))
  tangent = jnp.ones_like(one.density) * 100.0
  ref = jax.jvp(lambda d: traj(d, "reference"), (one.density,), (tangent,))
  ker = jax.jvp(lambda d: traj(d, "pallas"), (one.density,), (tangent,))
  for a, b in zip(ref, ker):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # ~3 min of compilation on 2 cores: `make test-all`
def test_box_plane_step_converged_is_mujoco_c(prims, c_traj):
  """With the solver run to convergence and all contacts, the box-plane step is MuJoCo C's
  own box-plane physics: it stays on C's trajectories through landings.

  Not every rollout: where a contact event amplifies float32 rounding (as a 1 µm change
  moves C itself by millimetres, docs/physics.md), one of these 16 parts from C by 0.34 mm
  within 0.1 s; so the bounds are on the 90th percentile and the median.
  """
  few = jax.tree.map(lambda x: x[:4], prims)
  converged = BoxPlaneSettings(iterations=10, ls_iterations=6, push_iterations=10,
                               push_ls_iterations=6, max_contacts=0)
  out = np.asarray(ppdjax.simulate(few, backend="box_plane", settings=converged))
  gap = _gap_mm(out, np.asarray(c_traj)[:4]).reshape(-1, 256)
  assert np.percentile(gap[:, :30].max(-1), 90) < 0.01 and np.median(gap) < 0.01


@pytest.mark.slow
def test_box_plane_reverse_mode_matches_forward_mode(prims):
  one = jax.tree.map(jnp.asarray, index(prims, 3))
  log_d = jnp.log(jnp.where(one.valid, one.density, 1.0))

  def loss(ld):
    return ppdjax.simulate(one.replace(density=jnp.exp(ld)), steps=10,
                           backend="box_plane")[..., :3].sum()

  grad = np.asarray(jax.grad(loss)(log_d))
  assert np.all(np.isfinite(grad))
  np.testing.assert_allclose(grad, jax.jacfwd(loss)(log_d), rtol=1e-3, atol=1e-6)


def test_hold_escapes_keeps_the_last_pose_inside_the_scene():
  t = np.zeros((2, 6, 7), np.float32)
  t[..., 3] = 1.0
  t[:, :, 0] = [0.0, 1.0, 5.0, 20.0, 1e7, np.nan]  # leaves at step 3, diverges at 5
  t[1, :, 0] = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]  # stays
  held = np.asarray(rollout_mjx.hold_escapes(jnp.asarray(t)))
  np.testing.assert_array_equal(held[0, :, 0], [0.0, 1.0, 5.0, 5.0, 5.0, 5.0])
  np.testing.assert_array_equal(held[1], t[1])
  thrown = np.zeros((2, 3, 7), np.float32)
  thrown[0, :, 0], thrown[0, :, 3] = 50.0, 1.0  # out from the first step: back on the sphere
  thrown[1] = np.nan
  held = np.asarray(rollout_mjx.hold_escapes(jnp.asarray(thrown)))
  np.testing.assert_allclose(held[0, :, 0], rollout_mjx.ESCAPE_DISTANCE)
  np.testing.assert_array_equal(held[1], np.tile([0.0, 0, 0, 1, 0, 0, 0], (3, 1)))


def test_a_candidate_launched_out_of_the_scene_stays_finite(prims, mjx_traj):
  """A push 1,000x the paper's on the lightest blocks: the rollout leaves the scene and
  is held there, finite, in the same compiled function."""
  light = prims.replace(density=jnp.full_like(prims.density, 50.0))
  traj = np.asarray(rollout_mjx.simulate(light, default_pushes(1e8)))
  assert np.all(np.isfinite(traj))
  far = np.linalg.norm(traj[..., -1, :3], axis=-1)
  assert far.max() > 1.0 and far.max() <= rollout_mjx.ESCAPE_DISTANCE + 1e-3
  assert np.all(np.isfinite(mjx_traj))
