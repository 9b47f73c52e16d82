"""The pendulum's strike (paper Sec. 5.3): its impulse, its checks, its records."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax.conventions import TIMESTEP, density_to_slot
from ppdjax.dataset import generation, materials, storage, towers
from ppdjax.sim import scene
from ppdjax.sim.pushes import pendulum_strike, push_points, strike_impulses
from conftest import index


@pytest.fixture(scope="module")
def prims():
  rng = np.random.default_rng(5)
  return ppdjax.primitives.stack([towers.sample_tower(rng, n, material_set="real")[0]
                                  for n in (2, 3, 4, 2)])


def test_strike_obeys_newtons_restitution(prims):
  """After the impulse J, the struck point separates from the ball at e times the speed
  of approach: u_point - u_ball = e v (rigid-body kinematics, computed here in NumPy)."""
  strike = pendulum_strike()
  v, m_ball, e = float(strike.magnitudes[0]), float(strike.striker_masses[0]), strike.restitution
  n = np.array([0.0, 1.0, 0.0])
  for i in range(4):
    one = jax.tree.map(jnp.asarray, index(prims, i))
    props = jax.tree.map(np.asarray, ppdjax.mass_properties(one))
    j = float(strike_impulses(one, strike)[0])
    r = np.asarray(push_points(one, strike))[0] - props.com
    omega = np.linalg.solve(props.inertia.astype(np.float64), np.cross(r, j * n))
    u_point = j / props.mass + n @ np.cross(omega, r)
    u_ball = v - j / m_ball
    np.testing.assert_allclose(u_point - u_ball, e * v, rtol=2e-4)


def test_heavier_objects_take_a_larger_impulse_and_move_slower(prims):
  strike = pendulum_strike()
  one = jax.tree.map(jnp.asarray, index(prims, 0))
  heavy = one.replace(density=one.density * 100)
  j, j_heavy = (float(strike_impulses(p, strike)[0]) for p in (one, heavy))
  limit = (1 + strike.restitution) * float(strike.magnitudes[0] * strike.striker_masses[0])
  assert j < j_heavy < limit and j_heavy > 0.9 * limit


def test_strike_sets_a_tower_moving_in_mujoco_c(prims):
  """In the C engine, the first step's momentum along the strike is the impulse, less the
  share the ground's friction takes as the tower tips (docs/physics.md)."""
  strike = pendulum_strike()
  traj = ppdjax.simulate(prims, strike, steps=2, backend="mujoco")  # (B, 1, 2, 7)
  for i in range(4):
    one = jax.tree.map(jnp.asarray, index(prims, i))
    rest = np.asarray(scene.rest_position(one))
    mass = float(ppdjax.mass_properties(one).mass)
    momentum = mass * (traj[i, 0, 0, 1] - rest[1]) / TIMESTEP
    share = momentum / float(strike_impulses(one, strike)[0])
    assert 0.3 < share < 1.01, (i, share)


@pytest.mark.parametrize("change, message", [
    (dict(striker_masses=np.float32([-1.0])), "striker_masses: expected finite"),
    (dict(striker_masses=np.float32([1.0, 2.0])), r"striker_masses: expected shape \(1,\)"),
    (dict(restitution=1.5), "restitution: expected a value in"),
])
def test_bad_strikes_are_named(change, message):
  with pytest.raises(ValueError, match=message):
    pendulum_strike().replace(**change).validate()


def test_pushes_survive_the_manifest():
  for pushes in (pendulum_strike(), ppdjax.default_pushes()):
    back = storage.pushes_from_record(generation.pushes_record(pushes))
    assert back.is_strike == pushes.is_strike and back.restitution == pushes.restitution
    for a, b in zip(back.arrays(), pushes.arrays()):
      if a is not None:
        np.testing.assert_array_equal(a, b)


def test_each_dataset_kind_has_its_pushes():
  cfg = generation.ml_collections.ConfigDict({"kind": "pendulum"})
  assert generation.pushes_of(cfg).is_strike
  assert generation.pushes_of(generation.ml_collections.ConfigDict({})).num == 4


def test_real_materials_take_their_one_density(prims):
  ids, density = towers.sample_configuration(np.random.default_rng(0), 200, "real")
  names = [materials.ALL_MATERIAL_NAMES[i] for i in ids]
  assert set(names) == set(materials.REAL_MATERIAL_NAMES)
  for name, d in zip(names, density):
    assert density_to_slot(d) + 1 == materials.REAL_MATERIALS[name]
  with pytest.raises(ValueError, match="material_set"):
    towers.sample_configuration(np.random.default_rng(0), 2, "plastic")
