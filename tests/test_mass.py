"""Mass properties against MuJoCo's compiler; transforms (jit, vmap, grad, jacfwd)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import primitives
from ppdjax.dataset import towers
from ppdjax.primitives import quat_to_mat
from ppdjax.sim import mass, scene
from conftest import index
from mujoco_reference import reference_model


def _random_object(rng, n):
  axis = rng.normal(size=(n, 3))
  axis /= np.linalg.norm(axis, axis=1, keepdims=True)
  angle = rng.uniform(0, np.pi, n)
  quat = np.column_stack([np.cos(angle / 2), axis * np.sin(angle / 2)[:, None]])
  return primitives.make(rng.uniform(0.02, 0.25, (n, 3)), rng.uniform(-0.3, 0.3, (n, 3)),
                         quat, rng.uniform(100, 10000, n))


def _rel(a, b):
  return np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()


@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_matches_mujoco_compiler_rotated_boxes(rng, n):
  for _ in range(5):
    p = _random_object(rng, n)
    ref = reference_model(p)
    props = ppdjax.mass_properties(jax.tree.map(jnp.asarray, p))
    rot = np.asarray(quat_to_mat(jnp.asarray(ref.body_iquat[1])))
    inertia_ref = rot @ np.diag(ref.body_inertia[1]) @ rot.T
    assert _rel(props.mass, ref.body_mass[1]) < 1e-5
    assert np.abs(np.asarray(props.com) - ref.body_ipos[1]).max() < 1e-5 * 0.5
    assert _rel(props.inertia, inertia_ref) < 1e-5


def test_derived_fields_match_set_const(rng):
  """invweight0 (which scales contact softness) as mj_setConst computes it."""
  for n in (2, 5):
    p = _random_object(rng, n)
    ref = reference_model(p)
    fields = scene.object_fields(jax.tree.map(jnp.asarray, p))
    np.testing.assert_allclose(fields["body_invweight0"], ref.body_invweight0, rtol=1e-5)
    np.testing.assert_allclose(fields["dof_invweight0"], ref.dof_invweight0, rtol=1e-5)
    np.testing.assert_allclose(fields["body_subtreemass"], ref.body_subtreemass, rtol=1e-5)


def test_invalid_boxes_contribute_nothing(rng):
  p = _random_object(rng, 3)
  garbage = p.replace(half_size=np.where(p.valid[:, None], p.half_size, np.float32(0.4)),
                      density=np.where(p.valid, p.density, np.float32(5000.0)))
  a, b = mass.mass_properties(p), mass.mass_properties(garbage)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_allclose(x, y, rtol=1e-6)


def test_jit_vmap_grad_jacfwd():
  batch = jax.tree.map(jnp.asarray, towers.sample_towers(3, 4))
  props = jax.jit(mass.mass_properties)(batch)
  assert props.mass.shape == (4,) and props.inertia.shape == (4, 3, 3)
  vm = jax.vmap(mass.mass_properties)(batch)
  np.testing.assert_allclose(vm.inertia, props.inertia, rtol=1e-6)
  one = index(batch, 0)

  def total(density):
    pr = mass.mass_properties(one.replace(density=density))
    return pr.mass + pr.com.sum() + jnp.trace(pr.inertia)

  g = jax.grad(total)(one.density)
  j = jax.jacfwd(total)(one.density)
  np.testing.assert_allclose(g, j, rtol=1e-5)
  assert np.all(np.asarray(g)[~np.asarray(one.valid)] == 0)
  eps = 1.0
  fd = [(total(one.density.at[k].add(eps)) - total(one.density.at[k].add(-eps))) / (2 * eps)
        for k in range(2)]
  np.testing.assert_allclose(np.asarray(g)[:2], fd, rtol=2e-2)


def test_principal_axes_jvp_finite_and_consistent(rng):
  """The custom JVP reconstructs d(inertia) and stays finite for symmetric objects."""
  p = jax.tree.map(jnp.asarray, _random_object(rng, 3))

  def tensor(density):
    inertia = mass.mass_properties(p.replace(density=density)).inertia
    moments, quat = mass.principal_axes(inertia)
    rot = quat_to_mat(quat)
    return rot @ jnp.diag(moments) @ rot.T

  direct = jax.jacfwd(lambda d: mass.mass_properties(p.replace(density=d)).inertia)(p.density)
  via_axes = jax.jacfwd(tensor)(p.density)
  np.testing.assert_allclose(via_axes, direct, rtol=1e-3, atol=1e-3 * float(jnp.abs(direct).max()))
  cube = jax.tree.map(jnp.asarray, primitives.make([[0.2, 0.2, 0.2]], [[0, 0, 0]]))
  jac = jax.jacfwd(lambda d: mass.principal_axes(
      mass.mass_properties(cube.replace(density=d)).inertia))(cube.density)
  assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(jac))


@pytest.mark.parametrize("core_density", [0.0, 2700.0])
def test_a_hollow_block_weighs_and_turns_as_its_shell_and_core(rng, core_density):
  """`inertia_scale` (dataset.hollow): a block of mean density with it has the mass, centre
  and inertia of its shell (six slabs) and core built box by box."""
  from ppdjax.dataset import hollow  # pylint: disable=import-outside-toplevel
  p = _random_object(rng, 2)
  shell, f = 7900.0, 0.7
  a, b, c = (np.asarray(p.half_size[0], np.float64))
  pieces = []  # (half size, centre in the block's frame) of the shell's slabs and the core
  for axis, (h, lo) in enumerate(zip((a, b, c), (f * a, f * b, f * c))):
    for sign in (-1, 1):
      half = [a, b, c]
      half[axis] = (h - lo) / 2
      for other in range(axis):  # the slabs of earlier axes hold the corners and edges
        half[other] = f * (a, b, c)[other]
      centre = np.zeros(3)
      centre[axis] = sign * (h + lo) / 2
      pieces.append((half, centre, shell))
  pieces.append(([f * a, f * b, f * c], np.zeros(3), core_density))
  rot = np.asarray(quat_to_mat(jnp.asarray(p.quat[0])))
  pieces = [x for x in pieces if x[2] > 0]
  explicit = primitives.make(
      np.asarray([x[0] for x in pieces] + [p.half_size[1]]),
      np.asarray([p.pos[0] + rot @ x[1] for x in pieces] + [p.pos[1]]),
      np.asarray([p.quat[0]] * len(pieces) + [p.quat[1]]),
      np.asarray([x[2] for x in pieces] + [p.density[1]]), num_slots=len(pieces) + 1)
  scale = np.ones(p.num_slots, np.float32)
  scale[0] = hollow.inertia_scale(shell, core_density, f)
  block = p.replace(density=p.density.copy(), inertia_scale=scale)
  block.density[0] = hollow.mean_density(shell, core_density, f)
  ours, ref = mass.mass_properties(block.validate()), mass.mass_properties(explicit)
  assert _rel(ours.mass, ref.mass) < 1e-5
  assert np.abs(np.asarray(ours.com) - np.asarray(ref.com)).max() < 1e-6
  assert _rel(ours.inertia, ref.inertia) < 1e-5
  assert _rel(ours.inertia, mass.mass_properties(p.replace(density=block.density)).inertia
              ) > 1e-3  # not what a uniform block of that mean density has


def test_a_bad_inertia_scale_is_named(rng):
  p = _random_object(rng, 2)
  for bad, what in ((np.ones(3, np.float32), "expected shape"),
                    (np.full(p.num_slots, np.nan, np.float32), "finite"),
                    (np.full(p.num_slots, -1.0, np.float32), "non-positive")):
    with pytest.raises(ValueError, match=f"inertia_scale.*{what}"):
      p.replace(inertia_scale=bad).validate()


def test_the_simulator_reads_the_inertia_scale():
  """MuJoCo C rolls a tower with a hollow block otherwise than the uniform tower of the same
  masses, and a scale of one as no scale."""
  from ppdjax.sim.pushes import pendulum_strike  # pylint: disable=import-outside-toplevel
  p = primitives.make([[0.06, 0.06, 0.12], [0.06, 0.06, 0.06]],
                      [[0.0, 0.0, 0.12], [0.0, 0.0, 0.30]], density=[2000.0, 5000.0])
  run = lambda q: ppdjax.simulate(q, pendulum_strike(), steps=120, backend="mujoco")
  uniform = run(p)
  same = run(p.replace(inertia_scale=np.ones(p.num_slots, np.float32)))
  scale = np.ones(p.num_slots, np.float32)
  scale[1] = 1.6
  hollow = run(p.replace(inertia_scale=scale))
  np.testing.assert_array_equal(uniform, same)
  assert np.abs(uniform[..., :3] - uniform[..., :1, :3]).max() > 0.01  # the strike moves it
  assert np.abs(hollow - uniform).max() > 1e-3
