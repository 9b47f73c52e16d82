"""The geometry stream: fresh towers, their voxels and the symmetries of the square."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import metrics
from ppdjax.dataset import stream, towers
from ppdjax.primitives import corners, make, stack


@pytest.fixture(scope="module")
def batch():
  return jax.tree.map(np.asarray, stream.sample_towers_jax(jax.random.key(3), 48))


def test_towers_are_stacked_and_fill_the_unit_cube(batch):
  n = batch.valid.sum(-1)
  assert n.min() >= 2 and n.max() <= 5 and len(set(n.tolist())) == 4
  c = np.asarray(corners(batch))
  for b in range(len(n)):
    pts = c[b, :n[b]].reshape(-1, 3)
    extent = pts.max(0) - pts.min(0)
    np.testing.assert_allclose(extent.max(), 1.0, rtol=1e-5)
    np.testing.assert_allclose((pts.max(0) + pts.min(0)) / 2, 0.0, atol=1e-5)
    top = batch.pos[b, :n[b] - 1, 2] + batch.half_size[b, :n[b] - 1, 2]
    bottom = batch.pos[b, 1:n[b], 2] - batch.half_size[b, 1:n[b], 2]
    np.testing.assert_allclose(top, bottom, atol=1e-5)  # each block rests on the one below
  assert np.all(batch.half_size[~batch.valid] == 0)


def test_size_distribution_matches_the_numpy_sampler():
  ours = stream.sample_towers_jax(jax.random.key(4), 2000)
  theirs = ppdjax.sample_towers(4, 2000)
  mean = lambda p: np.asarray(p.half_size)[np.asarray(p.valid)].mean(0)
  np.testing.assert_allclose(mean(ours), mean(theirs), rtol=0.05)
  assert abs(float(np.asarray(ours.valid).sum(-1).mean())
             - float(np.asarray(theirs.valid).sum(-1).mean())) < 0.15


def test_axis_aligned_voxels_equal_the_general_voxelizer(batch):
  np.testing.assert_array_equal(np.asarray(stream.voxelize_axis_aligned(batch)),
                                ppdjax.voxelize(batch).astype(bool))


def test_every_symmetry_maps_boxes_and_voxels_alike():
  rng = np.random.default_rng(0)
  prims = stack([make(*towers.sample_geometry(rng, rotate=0.5)) for _ in range(3)])
  voxels = jnp.asarray(ppdjax.voxelize(prims))
  p = jax.tree.map(jnp.asarray, prims)
  moved = []
  for code in range(8):
    v, q = jax.vmap(stream.transform, (0, 0, None))(voxels, p, code)
    np.testing.assert_array_equal(np.asarray(v), ppdjax.voxelize(jax.tree.map(np.asarray, q)))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(q.quat), axis=-1), 1.0, atol=1e-5)
    moved.append(np.asarray(v).sum())
    # the same solids: box volumes are kept
    np.testing.assert_allclose(np.prod(np.asarray(q.half_size), -1),
                               np.prod(np.asarray(p.half_size), -1), rtol=1e-5)
  assert len(set(moved)) == 1
  flip_x = jax.vmap(stream.transform, (0, 0, None))(voxels, p, 1)[1]
  np.testing.assert_allclose(flip_x.pos[..., 0], -p.pos[..., 0], atol=1e-6)


def test_geometry_batch_is_a_training_batch():
  b = jax.jit(stream.geometry_batch, static_argnums=1)(jax.random.key(0), 8)
  assert b["voxels"].shape == (8, 32, 32, 32) and b["voxels"].dtype == jnp.uint8
  prims = jax.tree.map(np.asarray, b["primitives"])
  prims.validate()
  # the labels describe the voxels: voxelizing them reproduces the batch
  np.testing.assert_array_equal(ppdjax.voxelize(prims), np.asarray(b["voxels"]))
  counts = metrics.shape_counts(prims, prims)
  assert np.all(np.asarray(counts["matched"]) == prims.valid.sum(-1))


def test_table4_shape_pool_is_the_stream_and_a_function_of_its_key():
  from ppdjax.eval.candidates import shape_pool
  key = jax.random.key(11)
  a, b = shape_pool(key, 64, 5), shape_pool(key, 64, 5)
  np.testing.assert_array_equal(np.asarray(a.half_size), np.asarray(b.half_size))
  np.testing.assert_array_equal(np.asarray(a.pos),
                                np.asarray(stream.sample_towers_jax(key, 64, 5).pos))
  other = shape_pool(jax.random.key(12), 64, 5)
  assert not np.allclose(np.asarray(other.half_size), np.asarray(a.half_size))
  blocks = np.asarray(a.valid).sum(-1)
  assert blocks.min() >= 2 and blocks.max() <= 5
