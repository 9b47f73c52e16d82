"""Primitives: construction, validation errors, ray-box geometry."""

import jax.numpy as jnp
import numpy as np
import pytest

from ppdjax import Primitives, primitives
from ppdjax.dataset import towers


def _tower():
  return primitives.make([[0.2, 0.2, 0.1], [0.1, 0.15, 0.2]], [[0, 0, -0.1], [0.05, 0, 0.2]],
                         density=[500.0, 2000.0])


def test_make_pads_to_five():
  p = _tower()
  assert p.half_size.shape == (5, 3) and p.quat.shape == (5, 4) and p.density.shape == (5,)
  assert p.valid.tolist() == [True, True, False, False, False]
  p.validate()


def test_sampled_towers_fit_the_unit_cube_and_validate():
  batch = towers.sample_towers(0, 20)
  Primitives.validate(batch)
  c = np.asarray(primitives.corners(batch))[np.asarray(batch.valid)]
  assert np.abs(c).max() <= 0.5 + 1e-6
  ext = c.reshape(-1, 3).max(0) - c.reshape(-1, 3).min(0)
  assert ext.max() > 0.5


@pytest.mark.parametrize("field,value,message", [
    ("half_size", np.zeros((5, 2), np.float32), "half_size: expected shape"),
    ("pos", np.full((5, 3), np.nan, np.float32), "pos: contains NaN"),
    ("density", np.float32([np.inf, 1, 1, 1, 1]), "density: contains NaN or inf"),
    ("quat", np.tile(np.float32([1, 1, 0, 0]), (5, 1)), "quat: not unit norm"),
    ("half_size", -np.ones((5, 3), np.float32), "half_size: negative"),
    ("density", np.float32([0, 1, 1, 1, 1]), "density: a valid box has a non-positive"),
    ("valid", np.zeros(5, bool), "valid: an object has no valid box"),
    ("valid", np.ones(5, np.int32), "valid: expected dtype bool"),
])
def test_validate_names_the_field(field, value, message):
  bad = _tower().replace(**{field: value})
  with pytest.raises(ValueError, match=message):
    bad.validate()


def test_ray_hits_first_face_and_misses():
  box = primitives.make([[0.5, 0.5, 0.5]], [[0, 0, 0]])
  t = primitives.ray_box_hits(jnp.array([2.0, 0, 0]), jnp.array([-1.0, 0, 0]), box)
  assert float(t[0]) == pytest.approx(1.5)
  assert np.all(np.isinf(np.asarray(t[1:])))  # invalid slots never hit
  t = primitives.ray_box_hits(jnp.array([2.0, 2, 0]), jnp.array([-1.0, 0, 0]), box)
  assert np.isinf(float(t[0]))


def test_ray_hits_rotated_box():
  q = np.float32([np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)])  # 45 degrees about z
  box = primitives.make([[0.5, 0.5, 0.5]], [[0, 0, 0]], quat=[q])
  t = primitives.ray_box_hits(jnp.array([2.0, 0, 0]), jnp.array([-1.0, 0, 0]), box)
  assert float(t[0]) == pytest.approx(2 - 0.5 * np.sqrt(2), abs=1e-5)
