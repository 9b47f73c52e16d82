"""Procedural tools and mesh normalisation (paper Sec. 5.2's inputs)."""

import numpy as np
import pytest
import trimesh

import ppdjax
from ppdjax import primitives
from ppdjax.dataset import meshes, tools
from ppdjax.dataset.materials import material_slots


@pytest.fixture(scope="module")
def tool_set():
  return tools.sample_tools(3, 48)


def test_tools_are_valid_rigid_objects(tool_set):
  assert {t.category for t in tool_set} == set(tools.CATEGORIES)
  for t in tool_set:
    assert 1 <= len(t.parts) <= 3 and len(t.names) == len(t.materials) == len(t.slots)
    for part, material, slot in zip(t.parts, t.materials, t.slots):
      assert part.is_watertight and part.volume > 0, (t.category, t.names)
      assert slot in material_slots(material)
    # parts touch but never overlap: their bounding boxes share at most a face
    for i in range(len(t.parts)):
      for j in range(i + 1, len(t.parts)):
        lo = np.maximum(t.parts[i].bounds[0], t.parts[j].bounds[0])
        hi = np.minimum(t.parts[i].bounds[1], t.parts[j].bounds[1])
        assert np.min(hi - lo) < 1e-9, (t.category, t.names[i], t.names[j])
  assert np.all(tool_set[0].densities == [ppdjax.conventions.slot_to_density(s)
                                          for s in tool_set[0].slots])


def test_tools_are_deterministic_and_distinct():
  a, b = tools.sample_tool(3, 5), tools.sample_tool(3, 5)
  assert a.category == b.category and a.slots == b.slots
  for p, q in zip(a.parts, b.parts):
    np.testing.assert_array_equal(p.vertices, q.vertices)
  assert not np.allclose(tools.sample_tool(3, 6, a.category).parts[0].vertices[:4],
                         a.parts[0].vertices[:4])
  with pytest.raises(ValueError, match="unknown tool category"):
    tools.sample_tool(0, 0, "chisel")


def test_normalize_is_the_project_frame_and_ignores_the_pose(tool_set):
  tool = next(t for t in tool_set if t.category == "hammer")
  parts, transform = meshes.normalize(list(tool.parts))
  union = trimesh.util.concatenate(parts)
  lo, hi = union.bounds
  np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
  np.testing.assert_allclose((hi - lo).max(), 1.0, rtol=1e-9)
  spread = np.asarray(union.vertices).std(0)
  assert spread[0] > spread[1] and spread[0] > spread[2]  # longest along x
  moved = trimesh.util.concatenate(tool.parts).copy()
  moved.apply_transform(transform)
  np.testing.assert_allclose(moved.vertices, union.vertices, atol=1e-9)
  # the same tool turned and moved normalises to the same object
  pose = trimesh.transformations.random_rotation_matrix(np.random.default_rng(1).random(3))
  pose[:3, 3] = [0.3, -2.0, 5.0]
  turned = [p.copy().apply_transform(pose) for p in tool.parts]
  again, _ = meshes.normalize(turned)
  np.testing.assert_allclose(trimesh.util.concatenate(again).vertices, union.vertices,
                             atol=1e-6)
  with pytest.raises(ValueError, match="expected a trimesh"):
    meshes.normalize([])


def test_voxelize_parts_matches_the_box_voxelizer():
  """A box mesh voxelizes as ppdjax.voxelize voxelizes the same box (sampled surface:
  at most the grazed voxels differ)."""
  half, pos = np.array([0.31, 0.12, 0.2]), np.array([0.05, -0.1, 0.02])
  mesh = trimesh.creation.box(extents=2 * half)
  mesh.apply_translation(pos)
  union, per_part = meshes.voxelize_parts([mesh])
  want = ppdjax.voxelize(primitives.stack([primitives.make(half[None], pos[None])]))[0] > 0
  assert per_part.shape == (1, 32, 32, 32) and np.array_equal(union, per_part[0])
  assert np.sum(union != want) <= 0.01 * want.sum(), (np.sum(union != want), want.sum())
