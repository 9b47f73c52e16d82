"""Procedural tools and mesh normalisation (paper Sec. 5.2's inputs)."""

import numpy as np
import pytest
import trimesh

import ppdjax
from ppdjax import box_overlap, primitives
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


def _joined_box_and_cylinder():
  box = trimesh.creation.box(extents=(0.4, 0.12, 0.1))
  cylinder = trimesh.creation.cylinder(radius=0.03, height=0.5, sections=32)
  cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
  cylinder.apply_translation([0.45, 0.0, 0.0])  # end to end along x, touching
  return [box, cylinder]


def _oriented_bounds(part: trimesh.Trimesh) -> primitives.Primitives:
  obb = part.bounding_box_oriented
  rot = obb.primitive.transform[:3, :3] * np.sign(np.linalg.det(obb.primitive.transform[:3, :3]))
  return primitives.make(np.asarray(obb.primitive.extents)[None] / 2,
                         obb.primitive.transform[:3, 3][None],
                         np.asarray(primitives.mat_to_quat(rot))[None])


def test_primitives_from_mesh_recovers_the_parts_of_a_composed_mesh():
  parts = _joined_box_and_cylinder()
  pose = trimesh.transformations.random_rotation_matrix(np.random.default_rng(4).random(3))
  posed = [p.copy().apply_transform(pose) for p in parts]
  prims, transform = ppdjax.primitives_from_mesh(posed, densities=[7800.0, 600.0])
  assert prims.valid.sum() == 2 and prims.density.shape == (5,)
  normalised = [p.copy().apply_transform(transform) for p in posed]
  for part, density in zip(normalised, (7800.0, 600.0)):
    truth = _oriented_bounds(part)
    iou = np.asarray(box_overlap.box_iou(truth, prims))[0]
    k = int(np.argmax(iou))
    assert iou[k] > 0.5, iou
    assert prims.density[k] == density  # the box takes its part's density
  prims.validate()
  with pytest.raises(ValueError, match="densities must give each"):
    ppdjax.primitives_from_mesh(parts, densities=[1.0])


def test_the_split_search_prunes_without_changing_the_boxes():
  """Cuts whose halves' hulls leave no room for the saving are not fitted: the same boxes,
  bit for bit, as fitting every cut, on a bent part (which splits) and on a tool
  (experiments/benchmarks/bench_tool_boxes.py checks 40 more)."""
  from ppdjax.dataset import mesh_boxes
  elbow = trimesh.util.concatenate([trimesh.creation.box([0.6, 0.1, 0.1]),
                                    trimesh.creation.box([0.1, 0.5, 0.1]).apply_translation(
                                        [0.25, 0.3, 0.0])])
  cases = [[elbow], meshes.normalize(list(tools.sample_tool(8, 0, "axe").parts))[0]]
  splits = 0
  for parts in cases:
    points, part = meshes.surface_samples(parts, 2_000)
    volume = sum(abs(p.volume) for p in parts)
    every, pruned = (mesh_boxes.fit_point_boxes(points, part, volume, prune=p)
                     for p in (False, True))
    assert len(every) == len(pruned)
    for a, b in zip(every, pruned):
      for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    splits += len(every) > len(parts)
  assert splits >= 1  # the elbow is cut: pruning had a winner to keep


def test_tool_boxes_cover_the_tools():
  for category in ("axe", "saw"):  # a bent handle, a blade thinner than a voxel
    tool = tools.sample_tool(8, 0, category)
    prims, transform = ppdjax.primitives_from_mesh(list(tool.parts), densities=tool.densities)
    parts = [p.copy().apply_transform(transform) for p in tool.parts]
    union, _ = meshes.voxelize_parts(parts)
    boxes = np.asarray(ppdjax.voxelize(primitives.stack([prims])))[0] > 0
    iou = (union & boxes).sum() / (union | boxes).sum()
    assert len(tool.parts) <= prims.valid.sum() <= 5 and iou > 0.6, (category, iou)
    assert set(prims.density[prims.valid]) <= set(tool.densities)


def test_load_object_reads_groups_and_components(tmp_path):
  parts = _joined_box_and_cylinder()
  scene = trimesh.Scene()
  for name, part in zip(("head", "handle"), parts):
    scene.add_geometry(part, node_name=name, geom_name=name)
  scene.export(tmp_path / "tool.glb")
  tool, transform = ppdjax.load_object(str(tmp_path / "tool.glb"),
                                       part_materials={"head": "metal", "handle": "wood"})
  assert tool.names == ("head", "handle") and tool.materials == ("metal", "wood")
  assert tool.densities[0] > tool.densities[1]
  lo, hi = trimesh.util.concatenate(tool.parts).bounds
  np.testing.assert_allclose((hi - lo).max(), 1.0, rtol=1e-6)
  trimesh.util.concatenate(parts).export(tmp_path / "tool.stl")  # one mesh: components
  tool, _ = ppdjax.load_object(str(tmp_path / "tool.stl"), part_densities=[7800, 700])
  assert tool.names == ("part0", "part1") and sorted(tool.densities) == [700.0, 7800.0]


def test_load_object_errors_name_the_problem(tmp_path):
  def write(name, mesh):
    mesh.export(tmp_path / name)
    return str(tmp_path / name)

  with pytest.raises(FileNotFoundError, match="no mesh file"):
    ppdjax.load_object(str(tmp_path / "missing.obj"))
  (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01")
  with pytest.raises(ValueError, match="cannot read"):
    ppdjax.load_object(str(tmp_path / "bad.ply"), part_materials="wood")
  box = trimesh.creation.box(extents=(0.3, 0.1, 0.1))
  open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)
  with pytest.raises(ValueError, match="not a closed surface"):
    ppdjax.load_object(write("open.stl", open_box), part_materials="wood")
  many = trimesh.util.concatenate([box.copy().apply_translation([i, 0, 0]) for i in range(6)])
  with pytest.raises(ValueError, match="6 parts; at most 5"):
    ppdjax.load_object(write("many.stl", many), part_materials="wood")
  path = write("box.obj", box)
  with pytest.raises(ValueError, match="unknown material"):
    ppdjax.load_object(path, part_materials="plastic")
  with pytest.raises(ValueError, match="does not have"):
    ppdjax.load_object(path, part_materials={"blade": "metal"})
  with pytest.raises(ValueError, match=r"must lie in \[100, 10000\]"):
    ppdjax.load_object(path, part_densities=[20000.0])
  with pytest.warns(UserWarning, match="every part is taken as wood"):
    tool, _ = ppdjax.load_object(path)
  assert tool.materials == ("wood",)


# --- labels: the legacy "category" mode, the "plausible" mode, thickness ---------------------

def _legacy_sample(seed, index):
  """An inline copy of `sample_tool`'s labels from before pieces existed: (category, names,
  materials, slots)."""
  rng = np.random.default_rng([seed, index])
  category = tools.CATEGORIES[rng.integers(len(tools.CATEGORIES))]
  names, _, materials = zip(*tools._BUILDERS[category](rng))
  return category, names, materials, tuple(int(rng.choice(material_slots(m))) for m in materials)


def test_the_category_labels_are_unchanged(tool_set):
  """`sample_tool` and `with_new_slots` draw what they drew before pieces existed (datasets
  stay reproducible): every part its own piece, one slot per part in part order."""
  for i, t in enumerate(tool_set):
    assert (t.category, t.names, t.materials, t.slots) == _legacy_sample(3, i)
    assert t.pieces == tuple(range(len(t.parts)))
    drawn = tools.with_new_slots(t, np.random.default_rng([3, i, 1]))
    rng = np.random.default_rng([3, i, 1])
    assert drawn.slots == tuple(int(rng.choice(material_slots(m))) for m in t.materials)
  # pinned: the geometry's rng calls (the builders) and the slot draws
  from ppdjax.dataset import tool_generation
  t = tools.sample_tool(5, 0)
  assert (t.category, t.materials) == ("spatula", ("ceramic", "metal"))
  assert [v.slots for v in tool_generation.density_variants(t, 5, 0, 4)] == [
      (34, 99), (56, 88), (34, 75), (52, 28)]


def _plausible_set(category, name):
  return next(m for names, m in tools.PLAUSIBLE_MATERIALS[category] if name in names)


def test_plausible_labels_share_a_piece_and_keep_the_geometry(tool_set):
  assert set(tools.PLAUSIBLE_MATERIALS) == set(tools.CATEGORIES)
  seen = {}
  for i, t in enumerate(tool_set):
    again = tools.sample_plausible_tool(3, i)
    assert again.names == t.names and again.category == t.category
    for p, q in zip(t.parts, again.parts):  # the same meshes, bit for bit
      np.testing.assert_array_equal(p.vertices, q.vertices)
      np.testing.assert_array_equal(p.faces, q.faces)
    for k in range(5):  # ~240 labellings
      u = tools.with_plausible_materials(t, np.random.default_rng([k, i]))
      for v in (u, tools.with_new_slots(u, np.random.default_rng([k, i, 1]))):
        for name, material, slot, piece in zip(v.names, v.materials, v.slots, v.pieces):
          assert material in _plausible_set(v.category, name) and material != "brick"
          assert slot in material_slots(material)
          seen.setdefault((v.category, name), set()).add(material)
          for name2, material2, slot2, piece2 in zip(v.names, v.materials, v.slots, v.pieces):
            if piece2 == piece:
              assert (material2, slot2) == (material, slot), (v.category, name, name2)
      want = {"wrench": (0, 0, 0), "screwdriver": (0, 1, 1)}.get(t.category, (0, 1))
      assert u.pieces == want, (t.category, u.pieces)
  for (category, name), materials in seen.items():  # every member of every set occurs
    assert materials == set(_plausible_set(category, name)), (category, name, materials)
  assert seen["hammer", "handle"] == {"wood", "ceramic", "metal"}
  # one piece, one density: a new configuration moves the wrench's parts together
  wrench = tools.sample_plausible_tool(3, 0, "wrench")
  slots = {tools.with_new_slots(wrench, np.random.default_rng(k)).slots for k in range(8)}
  assert len(slots) > 1 and all(len(set(s)) == 1 for s in slots)
  with pytest.raises(ValueError, match="share one material and slot"):
    tools.Tool("wrench", wrench.parts, wrench.names, wrench.materials, (70, 71, 70), (0, 0, 0))
  with pytest.raises(ValueError, match="pieces must give each"):
    tools.Tool("wrench", wrench.parts, wrench.names, wrench.materials, wrench.slots, (1, 0, 0))
  user = tools.Tool("user", wrench.parts, wrench.names, wrench.materials, wrench.slots)
  assert user.pieces == (0, 1, 2)
  with pytest.raises(ValueError, match="no plausible materials"):
    tools.with_plausible_materials(user, np.random.default_rng(0))


def _thickness_parameter(seed, index, category, drawn=False):
  """The builder's thickness draw (metres), its rng calls repeated: the wrench's `thick`,
  the saw's blade `bt` (`drawn`: the category was drawn first, not given)."""
  rng = np.random.default_rng([seed, index])
  if drawn:
    rng.integers(len(tools.CATEGORIES))
  if category == "wrench":
    rng.uniform(0.15, 0.25), rng.uniform(0.012, 0.02)
    return rng.uniform(0.005, 0.008)
  for lo, hi in ((0.1, 0.14), (0.07, 0.1), (0.02, 0.03), (0.25, 0.45), (0.06, 0.1)):
    rng.uniform(lo, hi)
  return rng.uniform(0.001, 0.002)


def test_part_thickness_is_the_builders_thickness():
  for category, part in (("wrench", 0), ("saw", 1)):
    tool = tools.sample_tool(8, 0, category)
    parts, transform = meshes.normalize(list(tool.parts))
    scale = np.linalg.norm(transform[:3, 0])
    thick = tools.part_thicknesses(parts)
    assert thick.shape == (len(parts),)
    np.testing.assert_allclose(thick[part], _thickness_parameter(8, 0, category) * scale,
                               atol=1e-3)
    np.testing.assert_allclose(tools.part_thicknesses(tool.parts)[part] * scale, thick[part],
                               rtol=1e-6)
  assert thick[1] < 1 / 32  # the saw's blade: thinner than a voxel


def test_tool_samples_record_thickness_in_both_modes():
  """One wrench through the whole row, in both modes (~7 s): each box records its part's
  thickness, 0 for padding; the plausible boxes share the wrench's one density."""
  from ppdjax.dataset import tool_generation
  index = next(i for i in range(100) if tools.sample_tool(0, i).category == "wrench")
  tool = tools.sample_tool(0, index)
  _, transform = meshes.normalize(list(tool.parts))
  want = _thickness_parameter(0, index, "wrench", drawn=True) * np.linalg.norm(transform[:3, 0])
  rows = {m: tool_generation.tool_samples(0, index, image_size=32, steps=30, configs=2,
                                          materials=m) for m in tool_generation.MATERIAL_MODES}
  for mode, both in rows.items():
    for row in both:
      valid = row["materials"] >= 0
      assert row["thickness"].dtype == np.float32
      assert row["thickness"].shape == row["density"].shape
      assert np.all(row["thickness"][~valid] == 0) and valid.sum() >= 1
      np.testing.assert_allclose(row["thickness"][valid], want, atol=1e-3)
      if mode == "plausible":
        assert len(set(row["density"][valid])) == 1  # one piece, one density
  for key in ("voxels", "half_size", "pos", "quat", "valid", "thickness"):  # one geometry
    np.testing.assert_array_equal(rows["category"][0][key], rows["plausible"][0][key])
  with pytest.raises(ValueError, match="tool_materials must be one of"):
    tool_generation.tool_samples(0, index, 32, 30, materials="random")


def test_the_labels_and_push_modes_read_the_data_config():
  import inspect

  import ml_collections

  from ppdjax.dataset import tool_generation
  assert tool_generation.materials_mode({}) == "category"  # data made before the key
  assert tool_generation.materials_mode({"tool_materials": "plausible"}) == "plausible"
  with pytest.raises(ValueError, match="tool_materials must be one of"):
    tool_generation.materials_mode({"tool_materials": "uniform"})

  class Recorder:
    def map(self, jobs):
      self.jobs = jobs
      return [[{"tower_id": np.int64(j[1])}] for j in jobs]

  cfg = ml_collections.ConfigDict(dict(num_tools=3, tools_per_shard=2, image_size=32, steps=30,
                                       split_fractions=(0.8, 0.1, 0.1),
                                       tool_materials="plausible", tool_push="by_volume"))
  workers = Recorder()
  tool_generation.generate_shard(cfg, 0, 1, workers)
  assert [j[1] for j in workers.jobs] == [2] and workers.jobs[0][-2:] == ("plausible",
                                                                          "by_volume")
  # the jobs are positional into tool_samples: the modes land on `materials` and `push`
  params = list(inspect.signature(tool_generation.tool_samples).parameters)
  assert params[len(workers.jobs[0]) - 2:len(workers.jobs[0])] == ["materials", "push"]
  assert tool_generation.push_mode({}) == "fixed"  # data made before the key
