"""Each convention has one home: defined once, and every consumer uses that definition."""

import os
import re

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax import conventions, metrics, primitives
from ppdjax.conventions import density_to_slot, density_to_slot_jax, slot_to_density
from ppdjax.dataset import storage, stream, towers, voxels
from ppdjax.infer import decompose, fit, joint, refine, sampling
from ppdjax.eval import baselines, evaluator, groups
from ppdjax.nn import losses

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _sources():
  for folder in ("ppdjax", "experiments"):
    for d, _, files in os.walk(os.path.join(ROOT, folder)):
      for f in files:
        if f.endswith(".py"):
          path = os.path.join(d, f)
          yield os.path.relpath(path, ROOT), open(path, encoding="utf-8").read()


# (what, a pattern that only a definition matches, its one home)
DEFINITIONS = [
    ("time step", r"^\s*TIMESTEP\s*=", "ppdjax/conventions.py"),
    ("slot width", r"^\s*SLOT_DENSITY\s*=", "ppdjax/conventions.py"),
    ("slot count", r"^\s*NUM_DENSITY_SLOTS\s*=", "ppdjax/conventions.py"),
    ("observation keys", r"OBS_KEYS\s*=\s*\(", "ppdjax/conventions.py"),
    ("slot -> density", r"\(\w+ \+ 1(\.0)?\) \* (SLOT_DENSITY|100)", "ppdjax/conventions.py"),
    ("Primitives fields", r"\"half_size\", \"pos\", \"quat\", \"density\"", None),
    ("bottom-to-top order", r"argsort\(.*pos\[\.\.\., 2\]|pos\)\[\.\.\., 2\]", None),
    ("bottom-to-top key", r"(jnp|xp)\.where\(prims\.valid, prims\.pos\[\.\.\., 2\]",
     "ppdjax/primitives.py"),
    ("rotation vector", r"arctan2\(", "ppdjax/metrics.py"),
    ("+Sample objective", r"- (self\.)?prior_weight \* ", "ppdjax/infer/sampling.py"),
    ("refine if closer", r"< distance\b|r_score < score", "ppdjax/infer/refine.py"),
    ("paper Table 2", r"18\.2, 59\.7, 84\.0", "ppdjax/report/tables.py"),
    ("paper Table 4", r"142\.2, 87\.1", "ppdjax/report/tables.py"),
    ("paper Table 5", r"2\.3, 4\.9, 7\.8, 10\.9", "ppdjax/report/tables.py"),
    ("paper shape F1", r"97\.5", "ppdjax/report/tables.py"),
]


def test_each_convention_is_defined_in_one_file():
  for what, pattern, home in DEFINITIONS:
    files = sorted({path for path, text in _sources()
                    if re.search(pattern, text, re.MULTILINE)})
    assert files == ([home] if home else []), (what, files)


def test_consumers_use_the_one_definition():
  assert losses.bottom_to_top is primitives.bottom_to_top
  assert evaluator.bottom_to_top is primitives.bottom_to_top
  assert baselines.bottom_to_top_order is primitives.bottom_to_top_order
  assert baselines.rotation_vector is metrics.rotation_vector
  assert decompose.refine_from_candidates is refine.refine_from_candidates
  assert evaluator.refine_batch is refine.refine_batch  # which calls refine_if_closer
  assert groups.fit_stage is decompose.fit_stage and decompose.fit_boxes is fit.fit_boxes
  assert decompose.density_prior is refine.density_prior
  assert joint.density_prior is refine.density_prior
  assert stream.TOUCH is voxels.TOUCH and fit.voxelizer is voxels  # one occupancy rule
  assert losses.density_to_slot_jax is conventions.density_to_slot_jax
  assert storage.OBS_KEYS is conventions.OBS_KEYS
  assert storage.FIELDS[4:4 + len(primitives.FIELDS)] == primitives.FIELDS


def test_bottom_to_top_orders_targets_baselines_and_evaluation_alike(rng):
  prims = towers.sample_towers(5, 8)
  shuffled = [rng.permutation(5) for _ in range(8)]
  prims = primitives.Primitives(*[np.stack([np.asarray(getattr(prims, f))[i][s]
                                            for i, s in enumerate(shuffled)])
                                  for f in primitives.FIELDS])
  ordered = primitives.bottom_to_top(prims)
  for z, v in zip(np.asarray(ordered.pos[..., 2]), np.asarray(ordered.valid)):
    n = int(v.sum())
    assert v[:n].all() and np.all(np.diff(z[:n]) > 0)
  slots = density_to_slot(np.asarray(ordered.density))
  np.testing.assert_array_equal(baselines.true_slots(prims),
                                np.where(ordered.valid, slots, -1))
  tgt = losses.targets(jax.tree.map(jnp.asarray, prims))
  np.testing.assert_array_equal(np.asarray(tgt["slot"])[np.asarray(ordered.valid)],
                                slots[np.asarray(ordered.valid)])


def test_boxes_on_one_level_go_along_x_and_towers_by_height(rng):
  # a tool lying flat: centres a fraction of a voxel apart in height, far apart along x;
  # its order must not hang on the sub-voxel heights (the voxels do not show them)
  voxel = 1.0 / conventions.VOXEL_RESOLUTION
  pos = np.array([[0.3, 0.0, 0.2 * voxel], [-0.4, 0.02, 0.0], [0.0, -0.1, -0.3 * voxel],
                  [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
  valid = np.array([True, True, True, False, False])
  order = lambda p, v: np.asarray(primitives.bottom_to_top_order(primitives.Primitives(
      jnp.full((5, 3), 0.05), jnp.asarray(p), jnp.tile(jnp.array([1.0, 0, 0, 0]), (5, 1)),
      jnp.ones(5), jnp.asarray(v))))
  np.testing.assert_array_equal(order(pos, valid)[:3], [1, 2, 0])
  assert set(order(pos, valid)[3:]) == {3, 4}  # padding last
  # a box more than a voxel higher starts a new level, whatever its x; levels chain
  pos[0, 2] = 1.5 * voxel
  np.testing.assert_array_equal(order(pos, valid)[:3], [1, 2, 0])
  pos[1, 2] = 2.9 * voxel  # now above box 0 by more than a voxel: the top level
  np.testing.assert_array_equal(order(pos, valid)[:3], [2, 0, 1])
  # towers: blocks are whole voxels apart in height, so the order is by height alone
  prims = towers.sample_towers(11, 64)
  key = np.where(np.asarray(prims.valid), np.asarray(prims.pos[..., 2]), np.inf)
  np.testing.assert_array_equal(np.asarray(primitives.bottom_to_top_order(prims)),
                                np.argsort(key, -1, kind="stable"))


def test_slots_and_densities_in_numpy_and_jax():
  slots = np.arange(100)
  np.testing.assert_array_equal(density_to_slot(slot_to_density(slots)), slots)
  np.testing.assert_array_equal(np.asarray(density_to_slot_jax(jnp.asarray(
      slot_to_density(slots)))), slots)
  np.testing.assert_array_equal(np.asarray(conventions.slot_to_density_jax(jnp.asarray(slots))),
                                slot_to_density(slots))
  assert density_to_slot(1e6) == 99 and density_to_slot(0.0) == 0
  assert slot_to_density(0) == conventions.MIN_DENSITY and slot_to_density(99) == \
      conventions.MAX_DENSITY


def test_selection_objective_is_what_select_densities_minimises():
  d, lp = jnp.array([0.10, 0.12, 0.30]), jnp.array([-9.0, -1.0, 0.0])
  assert int(jnp.argmin(sampling.selection_objective(d, lp, 0.0))) == 0
  assert int(jnp.argmin(sampling.selection_objective(d, lp, 0.01))) == 1
