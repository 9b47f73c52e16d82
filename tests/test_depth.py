"""Depth: the dataset's camera, the ray-cast depth of boxes against MuJoCo's, the depth fit."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import open_dataset
from ppdjax.dataset import camera as camera_lib
from ppdjax.dataset.depth import render_depth, render_depths
from ppdjax.infer import depth

from conftest import face_errors, index

SIZE = 64


@pytest.fixture(scope="module")
def towers():
  """Four fresh towers, their voxels, and their depth images rendered by MuJoCo."""
  from ppdjax.dataset import render
  prims = ppdjax.sample_towers(20261125, 4)
  with render.ObjectRenderer(SIZE, SIZE) as r:
    deps = np.stack([r.render(index(prims, i), np.zeros(5, int), np.arange(5))[1]
                     for i in range(4)])
  return prims, ppdjax.voxelize(prims), deps, camera_lib.camera_dict(SIZE, SIZE)


def test_ray_cast_depth_matches_mujocos(towers):
  prims, _, deps, cam = towers
  batched = np.asarray(render_depths(prims, cam))  # what generation stores
  for i in range(len(deps)):
    ours = np.asarray(render_depth(jax.tree.map(jnp.asarray, index(prims, i)), cam))
    np.testing.assert_allclose(batched[i], ours, atol=1e-6)
    seen = np.asarray(depth.object_mask(jnp.asarray(deps[i]), cam)).reshape(SIZE, SIZE)
    ours_seen = np.asarray(depth.object_mask(jnp.asarray(ours), cam)).reshape(SIZE, SIZE)
    assert seen.sum() > 100 and (seen == ours_seen).all()
    assert np.abs(ours - deps[i])[seen].max() < 1e-4  # metres
    floor = ~seen & (deps[i] < 4.0)  # the ground inside MuJoCo's 5 m plane
    assert np.abs(ours - deps[i])[floor].max() < 1e-3


def test_the_datasets_camera_explains_its_depth(tiny_dataset):
  ds = open_dataset(tiny_dataset, "test")
  cam = ds.camera
  size = ds[0]["depth"].shape
  assert (cam["height"], cam["width"]) == size
  np.testing.assert_allclose(cam["intrinsics"], camera_lib.intrinsics(*size))
  sample = ds[0]
  ours = np.asarray(render_depth(jax.tree.map(jnp.asarray, sample["primitives"]), cam))
  seen = np.asarray(depth.object_mask(jnp.asarray(sample["depth"]), cam)).reshape(size)
  assert np.abs(ours - sample["depth"])[seen].max() < 1e-4


@pytest.mark.slow  # about 20 s on 2 cores; `make test-all` (the fast suite stays under 10 minutes)
def test_depth_makes_the_faces_the_camera_sees_sub_voxel(towers):
  """Also under jax.jit (options and camera bound with functools.partial)."""
  prims, vox, deps, cam = towers
  plain = ppdjax.fit_boxes(vox)
  fitted = jax.jit(functools.partial(ppdjax.fit_boxes, camera=cam))(
      jnp.asarray(vox), depth=jnp.asarray(deps))
  before, after = face_errors(plain, prims), face_errors(fitted, prims)
  # faces move at most half a voxel from the voxel fit's, which is within half a voxel
  assert np.all(after <= 1 / 32 + 1e-4)
  # the camera looks from +x, -y, above: faces x-hi and y-lo face it
  assert np.median(after[:, [1, 3]]) < 1e-3 < np.median(before[:, [1, 3]])
  assert np.median(after) < 0.5 * np.median(before)
  assert np.array_equal(np.asarray(fitted.valid), np.asarray(plain.valid))


def test_depth_input_errors_are_named(towers):
  _, vox, deps, cam = towers
  with pytest.raises(ValueError, match="without its camera"):
    ppdjax.fit_boxes(vox, depth=deps)
  with pytest.raises(ValueError, match="without an image or a depth"):
    ppdjax.fit_boxes(vox, camera=cam)
  with pytest.raises(ValueError, match="32x32 images"):
    ppdjax.fit_boxes(vox, depth=deps, camera=camera_lib.camera_dict(32, 32))
  with pytest.raises(ValueError, match="expected shape"):
    ppdjax.fit_boxes(vox, depth=deps[:2], camera=cam)
  with pytest.raises(ValueError, match="finite"):
    ppdjax.fit_boxes(vox, depth=np.where(deps > 2, np.nan, deps), camera=cam)
  with pytest.raises(ValueError, match="missing"):
    ppdjax.fit_boxes(vox, depth=deps, camera={"height": SIZE})
  bad = dict(cam, camera_from_world=np.diag([1.0, 1.0, 2.0, 1.0]))
  with pytest.raises(ValueError, match="not a rotation"):
    ppdjax.fit_boxes(vox, depth=deps, camera=bad)


def test_sweep_centres_each_face_in_the_positions_its_pixels_accept():
  """A toy mismatch: box 0's x-hi face must lie in [0.10, 0.11] (pixels on either side
  disagree otherwise); box 1 sits on box 0 (tied z faces); every other face is unseen."""
  from ppdjax.infer import depth_fit
  faces = jnp.asarray([[-0.1, -0.1, -0.1, 0.1, 0.1, 0.1],
                       [-0.1, -0.1, 0.1, 0.1, 0.1, 0.3]], jnp.float32)
  ties = jnp.zeros((2, 2, 3), bool).at[0, 1, 2].set(True)  # 0's z-hi touches 1's z-lo
  lo, hi = faces - 0.015, faces + 0.015
  pixels = jnp.linspace(0.08, 0.13, 26)  # a pixel every 2 mm along x
  inside = (pixels >= 0.100) & (pixels <= 0.110)

  def mismatch(f):  # pixels the x-hi face explains wrongly, plus the tie's gap
    covered = pixels <= f[0, 3]
    return jnp.sum(covered != (pixels <= 0.1105)) + jnp.sum(inside & ~covered)

  out = np.asarray(depth_fit.sweep_faces(faces, lo, hi, ties, jnp.array([True, True]),
                                         mismatch))
  # the accepted run is [0.110, 0.112) (pixels at 0.110 in, 0.112 out): its middle
  assert abs(out[0, 3] - 0.111) < 3e-4
  np.testing.assert_allclose(np.delete(out, 3, axis=1)[0], np.delete(faces, 3, axis=1)[0],
                             atol=1e-6)  # unseen faces: the middle of their intervals
  assert out[0, 5] == pytest.approx(out[1, 2], abs=1e-6)  # the tie holds


def test_the_sweep_visits_the_valid_boxes_faces_wherever_they_sit():
  """`sweep_faces` loops over the valid boxes' faces only: an invalid slot between two
  valid boxes moves nothing and changes nothing about where the valid faces go."""
  from ppdjax.infer import depth_fit
  base = jnp.asarray([[-0.1, -0.1, -0.1, 0.1, 0.1, 0.1],
                      [-0.2, -0.2, 0.1, 0.2, 0.2, 0.3]], jnp.float32)
  target = base + jnp.asarray([0.004, -0.006, 0.0, 0.005, 0.003, -0.002])
  grid = jnp.linspace(-0.4, 0.4, 801)  # a "pixel" every mm

  def mismatch_of(rows):
    def mismatch(f):  # per valid face, the pixels between it and its target
      g = f[jnp.asarray(rows)]
      return jnp.sum((grid > jnp.minimum(g, target)[..., None])
                     & (grid <= jnp.maximum(g, target)[..., None]))
    return mismatch

  ties = lambda k: jnp.zeros((k, k, 3), bool)
  packed = depth_fit.sweep_faces(base, base - 0.015, base + 0.015, ties(2),
                                 jnp.array([True, True]), mismatch_of([0, 1]))
  junk = jnp.full((1, 6), 0.05)
  spread = jnp.concatenate([base[:1], junk, base[1:]])
  out = depth_fit.sweep_faces(spread, spread - 0.015, spread + 0.015, ties(3),
                              jnp.array([True, False, True]), mismatch_of([0, 2]))
  np.testing.assert_allclose(out[jnp.array([0, 2])], packed, atol=1e-7)
  np.testing.assert_array_equal(out[1], junk[0])  # the invalid slot stays
  assert np.abs(np.asarray(packed) - np.asarray(target)).max() < 1e-3  # and it did move


def test_objects_go_through_chunks_by_box_count_and_come_back_in_order():
  from ppdjax.infer import depth_fit
  counts = np.array([4, 2, 5, 2, 3, 1])
  valid = np.arange(5)[None] < counts[:, None]
  prims = ppdjax.Primitives(half_size=jnp.zeros((6, 5, 3)), pos=jnp.zeros((6, 5, 3)),
                            quat=jnp.zeros((6, 5, 4)), density=jnp.zeros((6, 5)),
                            valid=jnp.asarray(valid))
  tag = jnp.arange(6.0)
  out = depth_fit.map_by_box_count(lambda p, t: (jnp.sum(p.valid), 10 * t), prims, tag,
                                   chunk=4)
  np.testing.assert_array_equal(out[0], counts)
  np.testing.assert_array_equal(out[1], 10 * np.arange(6))


def test_chunks_by_slots_see_their_valid_boxes_first_and_put_them_back():
  """`map_by_box_count(slots=True)`: each chunk's function gets the valid boxes first, cut
  to the chunk's most valid boxes (at least 2); results go back to their slots, the slots
  cut off come back as they were, and objects come back in order."""
  from ppdjax.infer import depth_fit
  valid = np.array([[1, 0, 1, 1, 0], [1, 1, 0, 0, 0], [1, 1, 1, 1, 1], [0, 1, 0, 0, 0],
                    [1, 1, 1, 0, 0]], bool)
  b = len(valid)
  tag = jnp.arange(b, dtype=jnp.float32)
  prims = ppdjax.Primitives(
      half_size=jnp.broadcast_to(jnp.arange(5.0)[None, :, None], (b, 5, 3)),
      pos=jnp.zeros((b, 5, 3)), quat=jnp.zeros((b, 5, 4)),
      density=jnp.broadcast_to(tag[:, None], (b, 5)), valid=jnp.asarray(valid))

  def fn(p, t):  # marks the slots it saw with their count; keeps the slots' own sizes
    return p.replace(density=jnp.where(p.valid, 100.0 * p.valid.shape[0] + t, p.density))

  out = depth_fit.map_by_box_count(fn, prims, tag, chunk=2, slots=True)
  # sorted by count: [3 (1 box), 1 (2)] -> 2 slots, [4 (3), 0 (3)] -> 3, [2 (5)] -> 5
  seen = {3: 2, 1: 2, 4: 3, 0: 3, 2: 5}
  want = np.where(valid, 100.0 * np.array([seen[i] for i in range(b)])[:, None]
                  + np.arange(b)[:, None], np.arange(b)[:, None])
  np.testing.assert_array_equal(out.density, want)
  np.testing.assert_array_equal(out.half_size, prims.half_size)  # every slot in its place
  np.testing.assert_array_equal(out.valid, valid)
