"""Dataset building blocks: tower sampler, textures, voxels, rendering."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
from ppdjax import primitives
from ppdjax.conventions import density_to_slot
from ppdjax.dataset import materials, render, towers, voxels


def test_sampler_stacking_ranges_and_configurations():
  rng = np.random.default_rng(0)
  for _ in range(30):
    prims, ids = towers.sample_configurations(rng)
    assert prims.density.shape == (towers.CONFIGS_PER_TOWER, 5)
    for f in ("half_size", "pos", "quat", "valid"):  # configurations share the geometry
      assert np.all(np.asarray(getattr(prims, f)) == np.asarray(getattr(prims, f))[:1])
    valid = np.asarray(prims.valid[0])
    n = valid.sum()
    assert 2 <= n <= 5 and np.all(valid[:n]) and np.all(ids[:, n:] == -1)
    hs, pos = np.asarray(prims.half_size[0])[:n], np.asarray(prims.pos[0])[:n]
    lo, hi = (pos - hs).min(0), (pos + hs).max(0)
    assert (hi - lo).max() == pytest.approx(1.0, abs=1e-5)  # largest extent 1 m
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-5)  # centred on its box
    np.testing.assert_allclose(pos[1:, 2] - hs[1:, 2], pos[:-1, 2] + hs[:-1, 2], atol=1e-5)
    ratio = (hs[:, :2] / hs[:, 2:]).ravel()  # footprint/height within the sampled ranges
    assert ratio.min() > 0.5 / 1.0 - 1e-6 and ratio.max() < 1.5 / 0.3 + 1e-6
    for c in range(towers.CONFIGS_PER_TOWER):
      for k in range(n):
        slot = density_to_slot(prims.density[c, k])
        assert slot in materials.material_slots(materials.MATERIAL_NAMES[ids[c, k]])


def test_sampler_is_deterministic_and_validates_arguments():
  a = towers.sample_configurations(np.random.default_rng(5))
  b = towers.sample_configurations(np.random.default_rng(5))
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    assert np.array_equal(x, y)
  with pytest.raises(ValueError, match="num_blocks"):
    towers.sample_geometry(np.random.default_rng(0), 7)
  with pytest.raises(ValueError, match="rotate"):
    towers.sample_geometry(np.random.default_rng(0), 3, rotate=4.0)
  rotated, _ = towers.sample_configurations(np.random.default_rng(1), rotate=0.3,
                                            size_noise=0.1)
  rotated.validate()
  assert np.abs(np.asarray(primitives.corners(jax.tree.map(jnp.asarray, rotated)))).max() \
      <= 0.5 + 1e-5


def test_textures_identify_material_not_density():
  def features(img):
    grey = img.astype(float).mean(-1)
    return np.concatenate([img.reshape(-1, 3).mean(0), img.reshape(-1, 3).std(0),
                           [np.abs(np.diff(grey, axis=0)).mean(),
                            np.abs(np.diff(grey, axis=1)).mean()]])

  stats = {m: np.array([features(materials.texture(m, s)) for s in range(20)])
           for m in materials.MATERIAL_NAMES}
  scale = np.concatenate(list(stats.values())).std(0)  # z-score each feature
  stats = {m: v / scale for m, v in stats.items()}
  centroids = {m: v[:10].mean(0) for m, v in stats.items()}
  for m, v in stats.items():  # a nearest-centroid rule on colour statistics finds the family
    for x in v[10:]:
      assert min(centroids, key=lambda c: np.linalg.norm(x - centroids[c])) == m
  assert not np.array_equal(materials.texture("wood", 0), materials.texture("wood", 1))
  assert np.array_equal(materials.texture("wood", 3), materials.texture("wood", 3))
  # a texture is a function of (material, seed) alone: there is no density to leak
  import inspect
  assert list(inspect.signature(materials.texture).parameters) == ["material", "seed", "size"]


def _point_box_distance(points, prims):
  rot = np.asarray(primitives.quat_to_mat(jnp.asarray(prims.quat)))
  local = np.einsum("kji,pkj->pki", rot, points[:, None] - np.asarray(prims.pos)[None])
  outside = np.maximum(np.abs(local) - np.asarray(prims.half_size)[None], 0)
  d = np.linalg.norm(outside, axis=-1)
  return np.where(np.asarray(prims.valid)[None], d, np.inf).min(-1)


def test_voxels_against_point_sampling():
  rng = np.random.default_rng(2)
  for rotate in (0.0, 0.6):
    prims, _ = towers.sample_configurations(rng, 1, rotate=rotate)
    one = jax.tree.map(lambda x: x[0], prims)
    vox = voxels.voxelize(one)
    assert vox.shape == (32, 32, 32) and vox.dtype == np.uint8
    # completeness: every point inside a box lies in a filled voxel
    pts = []
    for k in np.flatnonzero(np.asarray(one.valid)):
      u = rng.uniform(-1, 1, (20000, 3)) * np.asarray(one.half_size[k])
      pts.append(u @ np.asarray(primitives.quat_to_mat(jnp.asarray(one.quat[k]))).T
                 + np.asarray(one.pos[k]))
    idx = np.clip(((np.concatenate(pts) + 0.5) * 32).astype(int), 0, 31)
    assert vox[idx[:, 0], idx[:, 1], idx[:, 2]].all()
    # soundness: a filled voxel's centre is within half a voxel diagonal of some box
    centers = voxels.voxel_centers()[vox.astype(bool)]
    assert _point_box_distance(centers, one).max() <= np.sqrt(3) / 64 + 1e-6
    # and an empty voxel's centre is outside every box
    empty = voxels.voxel_centers()[~vox.astype(bool)]
    assert _point_box_distance(empty, one).min() > 0


def test_render_rgb_and_depth():
  prims, ids = towers.sample_configurations(np.random.default_rng(3), 2)
  with render.ObjectRenderer(64, 80) as r:
    rgb0, depth0 = r.render(jax.tree.map(lambda x: x[0], prims), np.maximum(ids[0], 0),
                            np.arange(5))
    rgb1, _ = r.render(jax.tree.map(lambda x: x[1], prims), np.maximum(ids[1], 0),
                       np.arange(5))
  assert rgb0.shape == (64, 80, 3) and rgb0.dtype == np.uint8
  assert depth0.shape == (64, 80) and depth0.dtype == np.float32
  assert 1.0 < depth0.min() < 4.0  # the object in front of the camera
  if not np.array_equal(ids[0], ids[1]):
    assert not np.array_equal(rgb0, rgb1)  # new textures were uploaded
  with pytest.raises(ValueError, match="image size"):
    render.ObjectRenderer(8, 8)


def test_batch_renderer_workers_give_identical_images():
  prims, ids = towers.sample_configurations(np.random.default_rng(4), 3)
  seeds = np.arange(15).reshape(3, 5)
  with render.BatchRenderer(32, 32, workers=0) as r:
    rgb0, depth0 = r.render(prims, np.maximum(ids, 0), seeds)
  with render.BatchRenderer(32, 32, workers=2) as r:
    rgb2, depth2 = r.render(prims, np.maximum(ids, 0), seeds)
  assert rgb0.shape == (3, 32, 32, 3)
  assert np.array_equal(rgb0, rgb2) and np.array_equal(depth0, depth2)
