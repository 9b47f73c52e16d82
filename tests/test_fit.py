"""Box fitting to voxels: exact reading of axis-aligned towers, refinement, input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import box_overlap, metrics, primitives
from ppdjax.dataset import towers
from ppdjax.infer import fit

VOXEL = 1.0 / 32


def _voxelize(prims):
  """ppdjax.voxelize in chunks of 8 objects: one compiled shape for the whole module."""
  return ppdjax.voxelize(prims, chunk=8)


def _shape_counts(pred, true, chunk=16):
  """metrics.shape_counts in chunks (the IoU lattice of 64 objects at once is ~1 GB)."""
  f = jax.jit(metrics.shape_counts)
  parts = [f(*(jax.tree.map(lambda x: x[i:i + chunk], p) for p in (pred, true)))
           for i in range(0, len(true.valid), chunk)]
  return {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}


def _faces(prims):
  """(lo, hi) faces of axis-aligned boxes, (..., K, 3) each, in voxel coordinates (0..32)."""
  h, p = np.asarray(prims.half_size), np.asarray(prims.pos)
  return (p - h) / VOXEL + 16, (p + h) / VOXEL + 16


@pytest.fixture(scope="module")
def tower_set():
  """64 fresh axis-aligned towers (bottom to top) and their voxels."""
  true = jax.tree.map(np.asarray, primitives.bottom_to_top(ppdjax.sample_towers(4242, 64)))
  return true, _voxelize(true)


@pytest.fixture(scope="module")
def reading(tower_set):
  return jax.tree.map(np.asarray, fit.read_tower(tower_set[1]))


def test_read_tower_is_exact_on_axis_aligned_towers(tower_set, reading):
  true, vox = tower_set
  np.testing.assert_array_equal(reading.valid.sum(-1), true.valid.sum(-1))
  assert metrics.f1_from_counts(**_shape_counts(reading, true)) == 100.0
  (lo_t, hi_t), (lo_r, hi_r) = _faces(true), _faces(reading)
  err = np.concatenate([np.abs(lo_t - lo_r)[true.valid], np.abs(hi_t - hi_r)[true.valid]])
  assert err.max() <= 0.5 + 1e-4, err.max()  # faces at voxel centres: within half a voxel
  assert 0.2 < err.mean() < 0.3  # ~uniform in [0, 0.5]: the face is unknown inside its voxel
  np.testing.assert_array_equal(_voxelize(reading), vox)  # reproduces the input
  np.testing.assert_array_equal(reading.quat[reading.valid], [[1, 0, 0, 0]] * reading.valid.sum())
  assert np.all(reading.density == np.where(reading.valid, 1000.0, 0.0))
  assert np.all(reading.half_size[~reading.valid] == 0) and np.all(reading.pos[~reading.valid] == 0)


def _box(lo, hi):
  """(half size, centre) in metres of a box given by voxel coordinates lo..hi (0..32)."""
  lo, hi = np.float32(lo) * VOXEL - 0.5, np.float32(hi) * VOXEL - 0.5
  return (hi - lo) / 2, (hi + lo) / 2


def test_read_tower_edge_cases():
  cases = [  # boxes as (lo, hi) voxel coordinates, and the boxes read back
      # interface exactly on a voxel boundary, rectangles not nested: no straddling slice
      [([4, 4, 0], [20, 12, 10]), ([10, 8, 10], [28, 30, 32])],
      # rectangles nested, interface inside a slice of the larger one
      [([2, 2, 0], [30, 30, 12.4]), ([8, 8, 12.4], [20, 20, 32])],
      # a pure block one slice thick between two others
      [([0, 0, 0], [32, 20, 10]), ([4, 5, 10], [14, 15, 11]), ([2, 3, 11], [30, 32, 32])],
      # identical voxel rectangles merge: two boxes read as one (documented limitation)
      [([4.2, 4.2, 0], [20.6, 12.6, 12.4]), ([4.4, 4.1, 12.4], [20.8, 12.7, 32])],
  ]
  cases += [[(lo[1::-1] + lo[2:], hi[1::-1] + hi[2:]) for lo, hi in c] for c in cases]  # x <-> y
  prims = primitives.stack([primitives.make(*zip(*[_box(lo, hi) for lo, hi in c]))
                            for c in cases])
  vox = _voxelize(prims)
  got = jax.tree.map(np.asarray, fit.read_tower(vox))
  np.testing.assert_array_equal(got.valid.sum(-1), [2, 2, 3, 1] * 2)
  np.testing.assert_array_equal(_voxelize(got), vox)
  (lo_t, hi_t), (lo_r, hi_r) = _faces(prims), _faces(got)
  ok = prims.valid & (got.valid.sum(-1) == prims.valid.sum(-1))[:, None]  # all but the merge
  assert np.abs(lo_t - lo_r)[ok].max() <= 0.5 + 1e-4
  assert np.abs(hi_t - hi_r)[ok].max() <= 0.5 + 1e-4
  np.testing.assert_allclose([hi_r[0, 0, 2], lo_r[0, 1, 2]], 10.0, atol=1e-4)  # the boundary
  np.testing.assert_allclose([hi_r[1, 0, 2], lo_r[1, 1, 2]], 12.5, atol=1e-4)  # nested
  np.testing.assert_allclose([lo_r[3, 0, 2], hi_r[3, 0, 2]], [0.5, 31.5], atol=1e-4)  # merged


def _turn(quat, angle, rng):
  """Quaternions (n, 4) turned by `angle` radians about random axes."""
  axis = rng.normal(size=(len(quat), 3))
  axis /= np.linalg.norm(axis, axis=1, keepdims=True)
  q = np.column_stack([np.full(len(quat), np.cos(angle / 2)), axis * np.sin(angle / 2)])
  return np.asarray(primitives.quat_mul(jnp.asarray(q, jnp.float32), jnp.asarray(quat)))


def _noisy(prims, rng, voxels=1.0, degrees=10.0):
  """Boxes with N(0, `voxels`) noise on centres and half sizes, turned by `degrees`."""
  k = prims.valid.shape[0]
  half = np.maximum(prims.half_size + rng.normal(0, voxels * VOXEL, (k, 3)), VOXEL / 2)
  pos = prims.pos + rng.normal(0, voxels * VOXEL, (k, 3))
  v = prims.valid[:, None]
  return primitives.Primitives(np.where(v, half, 0).astype(np.float32),
                               np.where(v, pos, 0).astype(np.float32),
                               _turn(prims.quat, np.deg2rad(degrees), rng), prims.density,
                               prims.valid)


@pytest.mark.slow  # a robustness cross-check: about 30 s on 2 cores; `make test-all`
def test_fit_recovers_rotated_boxes_from_noisy_starts():
  rng = np.random.default_rng(77)
  true = [primitives.make(*towers.sample_geometry(rng, rotate=0.3)) for _ in range(6)]
  true += [primitives.make(*towers.sample_geometry(rng, n, rotate=np.pi)) for n in (1, 2)]
  true = primitives.stack(true)
  vox = _voxelize(true)
  start = primitives.stack([_noisy(jax.tree.map(lambda x: x[i], true), rng) for i in range(8)])
  got = fit.fit_boxes(vox, start)
  filled = vox.reshape(8, -1).sum(-1)
  miss = lambda p: (_voxelize(p) != vox).reshape(8, -1).sum(-1) / filled
  miss_start, miss_fit = miss(start), miss(got)
  iou = np.asarray(box_overlap.box_iou(jax.tree.map(jnp.asarray, true), got)).max(-1)
  mean_iou = np.where(true.valid, iou, 0).sum(-1) / true.valid.sum(-1)
  print("disagreement", miss_start.round(3), "->", miss_fit.round(3), "IoU", mean_iou.round(2))
  assert np.all(miss_fit < miss_start / 5)  # starts disagree on ~40 % of filled voxels
  assert np.median(miss_fit) < 0.02
  assert np.sum(mean_iou > 0.7) >= 7 and mean_iou.mean() > 0.8
  np.testing.assert_allclose(np.linalg.norm(np.asarray(got.quat), axis=-1), 1.0, atol=1e-5)
  np.testing.assert_array_equal(got.valid.sum(-1), true.valid.sum(-1))


@pytest.fixture(scope="module")
def fitted_towers(tower_set):
  """fit_boxes on 16 of the towers, no init, as a (2, 8) batch (the batch the other tests
  fit: one compilation)."""
  out = jax.tree.map(np.asarray, fit.fit_boxes(tower_set[1][:16]))
  return jax.tree.map(lambda x: x.reshape((2, 8) + x.shape[1:]), out)


def test_fit_is_jittable_and_batched(tower_set, fitted_towers):
  """fit_boxes traces under jax.jit and keeps leading batch axes (traced, not compiled
  again: the values are the batch the others fit)."""
  vox = tower_set[1][:16].reshape(2, 8, 32, 32, 32)
  shapes = jax.eval_shape(jax.jit(fit.fit_boxes), vox)
  assert shapes.batch_shape == (2, 8) and shapes.num_slots == 5
  assert jax.tree.map(np.shape, shapes) == jax.tree.map(np.shape, fitted_towers)
  primitives.validate(fitted_towers)
  z = np.where(fitted_towers.valid, fitted_towers.pos[..., 2], 1e9)
  assert np.all(np.diff(z, axis=-1)[fitted_towers.valid[..., 1:]] >= 0)  # bottom to top


def test_fit_without_init_is_exact_on_axis_aligned_towers(tower_set, fitted_towers):
  true, vox = tower_set
  got = jax.tree.map(lambda x: x.reshape((16,) + x.shape[2:]), fitted_towers)
  top = jax.tree.map(lambda x: x[:16], true)
  assert metrics.f1_from_counts(**_shape_counts(got, top)) == 100.0
  np.testing.assert_array_equal(_voxelize(got), vox[:16])


@pytest.mark.slow  # a second compiled fit (~20 s on 2 cores): `make test-all`
def test_exact_readings_skip_the_search_with_the_same_answer(tower_set, fitted_towers):
  """A batch of towers takes the fast path (every exact reading wins); one rotated box
  among them sends the whole batch through the search, which must agree on the towers."""
  true, vox = tower_set
  rotated = primitives.make(*towers.sample_geometry(np.random.default_rng(5), 1, rotate=0.5))
  mixed = np.concatenate([vox[:15], _voxelize(primitives.stack([rotated]))])
  got = jax.tree.map(np.asarray, fit.fit_boxes(mixed))
  fast = jax.tree.map(lambda x: x.reshape((16,) + x.shape[2:])[:15], fitted_towers)
  for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[:15], got)), jax.tree.leaves(fast)):
    np.testing.assert_array_equal(a, b)
  assert got.valid[15].sum() == 1  # the rotated box was fitted, not read as a tower


def test_rejects_bad_input(tower_set):
  vox = tower_set[1][:2]
  with pytest.raises(ValueError, match=r"voxels: expected shape \(\.\.\., 32, 32, 32\)"):
    fit.fit_boxes(np.zeros((32, 32, 31), np.uint8))
  with pytest.raises(ValueError, match="exactly 0 or 1"):
    fit.fit_boxes(vox * np.float32(0.5))
  with pytest.raises(ValueError, match="dtype"):
    fit.read_tower(vox.astype(np.complex64))
  with pytest.raises(ValueError, match="all empty"):
    fit.fit_boxes(np.concatenate([vox, np.zeros_like(vox[:1])]))
  with pytest.raises(ValueError, match="init: batch shape"):
    fit.fit_boxes(vox, jax.tree.map(lambda x: x[:3], tower_set[0]))
  assert fit.check_voxels(vox.astype(np.float32)) == (2,)  # 0/1 floats and bools are fine
  assert fit.check_voxels(vox.astype(bool)) == (2,)


def test_fit_puts_the_longest_axis_on_the_grid_boundary(tower_set, reading):
  """Objects are normalised to a 1 m largest extent: along the one axis that spans the
  grid, the face that bounds the object lies on ±0.5 m, where the fit now puts it (the
  reading, from the voxels alone, leaves it half a voxel in); no face moves farther from
  the truth than half a voxel, and the boxes still voxelize as the input."""
  # half the towers, in batches of 16, the size the other tests fit (one compilation)
  true, vox = jax.tree.map(lambda x: x[:32], tower_set)
  reading = jax.tree.map(lambda x: x[:32], reading)
  snapped = jax.tree.map(lambda *x: np.concatenate(x), *[
      jax.tree.map(np.asarray, fit.fit_boxes(vox[i:i + 16])) for i in range(0, len(vox), 16)])
  spans = np.stack([vox.any((2, 3)).all(-1), vox.any((1, 3)).all(-1), vox.any((1, 2)).all(-1)], -1)
  one = spans.sum(-1) == 1
  assert one.mean() > 0.7  # most towers: only their height spans the grid
  (lo_t, hi_t), (lo_s, hi_s), (lo_r, hi_r) = _faces(true), _faces(snapped), _faces(reading)
  err_s = np.abs(np.stack([lo_t - lo_s, hi_t - hi_s]))[:, true.valid]
  err_r = np.abs(np.stack([lo_t - lo_r, hi_t - hi_r]))[:, true.valid]
  assert err_s.max() <= 0.5 + 1e-4 and err_s.mean() < err_r.mean() - 0.02
  moved = 0
  for n in np.flatnonzero(one):
    a = int(np.argmax(spans[n]))
    valid = true.valid[n]
    for faces, sign in ((hi_s[n], 1), (lo_s[n], -1)):
      at = np.isclose(faces[valid, a], 16 + 16 * sign, atol=1e-3)
      truth = (hi_t if sign > 0 else lo_t)[n][valid, a]
      reached = np.isclose(truth, 16 + 16 * sign, atol=1e-3)
      if reached.sum() == 1 and np.isclose(faces[valid, a], (faces[valid, a].max() if sign > 0
                                                           else faces[valid, a].min())).sum() == 1:
        assert at.sum() == 1 and np.array_equal(at, reached), (n, a, sign)
        moved += 1
  assert moved >= one.sum()  # at least one bounding face per such tower went to the boundary
  np.testing.assert_array_equal(_voxelize(snapped), vox)
  plain = jax.tree.map(np.asarray, fit.fit_boxes(vox[:16], unit_extent=False))
  for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(jax.tree.map(lambda x: x[:16], reading))):
    np.testing.assert_allclose(a, b, atol=1e-6)  # without it: the reading


def test_faces_drawn_within_the_voxels_tolerance(tower_set):
  """+Fit+Sample's face draws (`faces.spread_faces`): every candidate voxelizes as the
  input, candidate 0 is the fit, touching faces stay touching, faces on the grid boundary
  stay, the rest spread over most of their half-voxel interval, and each candidate is
  centred on its bounding box."""
  from ppdjax.infer import faces
  _, vox = tower_set
  fitted = jax.tree.map(lambda x: x[:8], fit.fit_boxes(vox[:16]))  # the others' batch size
  cands = jax.tree.map(np.asarray, jax.jit(jax.vmap(lambda p, k: faces.spread_faces(p, k, 32)))(
      fitted, jax.random.split(jax.random.key(3), 8)))
  np.testing.assert_array_equal(_voxelize(cands), np.repeat(vox[:8, None], 32, 1))
  for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[:, 0], cands)),
                  jax.tree.leaves(jax.tree.map(np.asarray, fitted))):
    np.testing.assert_allclose(a, b, atol=1e-6)
  lo, hi = _faces(cands)
  f_lo, f_hi = _faces(jax.tree.map(lambda x: np.asarray(x)[:, None], fitted))
  valid = cands.valid
  for n in range(8):
    k = valid[n, 0].sum()
    np.testing.assert_allclose(hi[n, :, :k - 1, 2], lo[n, :, 1:k, 2], atol=1e-4)  # stacked
  move = np.abs(np.concatenate([lo - f_lo, hi - f_hi], -1))[valid]  # (.., 6) voxels
  boundary = np.broadcast_to(np.isclose(np.abs(np.concatenate([f_lo, f_hi], -1) - 16), 16,
                                        atol=1e-3), lo.shape[:3] + (6,))[valid]
  assert move[boundary].max() < 1e-3 and move.max() < 0.5
  assert np.percentile(move[~boundary], 90) > 0.3  # the draws cover the interval
  bound = np.where(valid[..., None], np.stack([lo, hi]), np.nan)
  np.testing.assert_allclose(np.nanmin(bound[0], 2) + np.nanmax(bound[1], 2), 32, atol=1e-3)


def test_unit_extent_snap_on_turned_boxes_and_draws_keep_an_off_centre_fit():
  """The snap moves the right face of a box whose axes point against the world's (turned
  180° about z and 90° about x); face draws keep an object's bounding-box centre where it
  is (a fit snapped at one end only is off the origin), candidate 0 being the input."""
  from ppdjax.infer import faces
  # one box 0.4 x 1.0 x 0.6 m along its own axes, turned so that they point along -x, -z
  # and -y; z spans the grid, and its z faces were read half a voxel in
  half = np.array([[0.2, 0.5 - VOXEL / 2, 0.3]], np.float32)
  turned = np.array([[0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5)]], np.float32)  # (w, x, y, z)
  box = primitives.make(half, np.zeros((1, 3), np.float32), turned)
  rot = np.asarray(primitives.quat_to_mat(box.quat))[0]
  assert np.isclose(rot[2, 1], -1.0)  # its second axis points down
  vox = np.zeros((32, 32, 32), np.uint8)
  vox[10:22, 6:26, :] = 1  # a full column along z only
  snapped = jax.jit(faces.snap_unit_extent)(box, jnp.asarray(vox))  # one program, not op by op
  np.testing.assert_allclose(snapped.half_size[0], [0.2, 0.5, 0.3], atol=1e-6)
  np.testing.assert_allclose(snapped.pos[0], 0.0, atol=1e-6)  # both z ends moved out
  # off the origin: a tower whose top face was not snapped (two boxes reach it alike)
  tower = primitives.make(np.array([[0.2, 0.2, 0.25], [0.1, 0.1, 0.234375],
                                    [0.05, 0.05, 0.234375]], np.float32),
                          np.array([[0, 0, -0.25], [-0.1, 0, 0.234375], [0.15, 0, 0.234375]],
                                   np.float32))
  centre = np.asarray(faces.bounds_centre(tower))
  assert abs(centre[2]) > 1e-3
  cands = jax.jit(faces.spread_faces, static_argnums=2)(tower, jax.random.key(0), 16)
  for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[0], cands)), jax.tree.leaves(tower)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  centres = np.asarray(jax.vmap(faces.bounds_centre)(cands))
  np.testing.assert_allclose(centres, np.broadcast_to(centre, centres.shape), atol=1e-6)
  with pytest.raises(ValueError, match=r"face_spread must be in \[0, 0.5\]"):
    faces.spread_faces(tower, jax.random.key(0), 4, spread=0.8)
