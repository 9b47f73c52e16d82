"""+Joint: box faces and densities fitted together to the motion and the depth image."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppdjax.dataset import camera as camera_lib
from ppdjax.dataset import depth as depth_lib
from ppdjax.dataset import towers
from ppdjax.infer.joint import refine_joint
from ppdjax.infer.refine import refine_densities
from ppdjax.primitives import make
from ppdjax.sim.simulate import simulate

STEPS = 48


def faces(p):
  return np.concatenate([np.asarray(p.pos - p.half_size), np.asarray(p.pos + p.half_size)], -1)


@pytest.mark.slow
def test_joint_fit_recovers_faces_and_densities_of_a_two_block_tower():
  """Faces off by up to 3.6 mm and densities by x1.5 / x0.7: the joint fit brings the faces
  back within 0.2 mm and the densities within 2 %, where refining the densities alone on
  the wrong boxes compensates (the light block's density lands 35 % low)."""
  rng = np.random.default_rng(7)
  true = make(*towers.sample_geometry(rng, 2), np.array([800.0, 4000.0]), 5)
  observed = simulate(true, steps=STEPS)
  cam = camera_lib.camera_dict(112, 112)
  depth = depth_lib.render_depths(jax.tree.map(lambda x: jnp.asarray(x)[None], true), cam)[0]
  off = np.zeros((5, 3))
  off[:2] = rng.uniform(-6e-3, 6e-3, (2, 3))
  start = true.replace(half_size=true.half_size + off,
                       density=true.density * jnp.array([1.5, 0.7, 1, 1, 1]))
  fit = jax.jit(lambda p: refine_joint(
      p, observed, depth=depth, intrinsics=jnp.asarray(cam["intrinsics"], jnp.float32),
      camera_from_world=jnp.asarray(cam["camera_from_world"], jnp.float32), steps=8,
      warmup_steps=24))(start)
  assert np.abs(faces(start) - faces(true))[:2].max() > 3e-3
  assert np.abs(faces(fit.primitives) - faces(true))[:2].max() < 2e-4
  np.testing.assert_allclose(fit.primitives.density[:2], true.density[:2], rtol=0.02)
  assert float(fit.cost) < 1e-3 * float(fit.cost_start)
  alone, _ = jax.jit(lambda p: refine_densities(p, observed, steps=8, warmup_steps=24))(start)
  assert abs(float(alone.density[0]) / 800.0 - 1) > 0.2
