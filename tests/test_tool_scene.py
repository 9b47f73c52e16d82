"""A tool's own physics and image (ppdjax.dataset.tool_scene), checked against the towers'."""

import numpy as np
import pytest
import trimesh

import ppdjax
from ppdjax import primitives
from ppdjax.dataset import meshes, tool_scene, tools
from conftest import cli_module


def test_a_box_tool_moves_as_the_same_box_tower():
  """The tool path (mesh geom, explicit inertia, ray-cast push point) against the towers'
  C engine (box geom, box formulas): the same box, the same pushes."""
  half, pos = np.array([0.4, 0.15, 0.1]), np.array([0.02, -0.01, 0.0])
  box = trimesh.creation.box(extents=2 * half).apply_translation(pos)
  prims = primitives.stack([primitives.make(half[None], pos[None], density=2000.0)])
  pushes = ppdjax.default_pushes()
  want = np.asarray(ppdjax.simulate(prims, pushes, steps=64, backend="mujoco"))[0]
  got = tool_scene.simulate_tool([box], [2000.0], pushes, steps=64)
  gap = np.linalg.norm(got[..., :3] - want[..., :3], axis=-1)
  assert gap.max() < 1e-5, gap.max()
  assert np.linalg.norm(want[:, -1, :3] - want[:, 0, :3], axis=-1).min() > 0.01  # it moved


def test_a_tool_simulated_with_given_mass_properties():
  """`simulate_tool(inertial=)`: the box's own (ppdjax.mass_properties) changes nothing;
  twice its mass with the same shape moves it less far."""
  half = np.array([0.4, 0.15, 0.1])
  box = trimesh.creation.box(extents=2 * half)
  prims = primitives.stack([primitives.make(half[None], np.zeros((1, 3)), density=2000.0)])
  mp = ppdjax.mass_properties(prims)
  own = (float(mp.mass[0]), np.asarray(mp.com[0], np.float64), np.asarray(mp.inertia[0], np.float64))
  pushes = ppdjax.default_pushes()  # the towers' push: a 96 kg box slides
  plain = tool_scene.simulate_tool([box], [2000.0], pushes, steps=64)
  same = tool_scene.simulate_tool([box], [2000.0], pushes, steps=64, inertial=own)
  np.testing.assert_allclose(same, plain, atol=1e-6)
  heavy = tool_scene.simulate_tool([box], [2000.0], pushes, steps=64,
                                   inertial=(2 * own[0], own[1], 2 * own[2]))
  travel = lambda t: np.linalg.norm(t[:, -1, :3] - t[:, 0, :3], axis=-1)
  assert np.all(travel(heavy) < travel(plain))


def test_mass_properties_add_up_as_the_box_formulas():
  halves = np.array([[0.3, 0.1, 0.05], [0.05, 0.05, 0.2]])
  centres = np.array([[0.0, 0.0, 0.0], [0.35, 0.0, 0.15]])
  densities = [7800.0, 600.0]
  parts = [trimesh.creation.box(extents=2 * h).apply_translation(c)
           for h, c in zip(halves, centres)]
  mass, com, inertia = tool_scene.mass_properties(parts, densities)
  want = ppdjax.mass_properties(primitives.make(halves, centres, density=np.array(densities),
                                                num_slots=2))
  np.testing.assert_allclose(mass, want.mass, rtol=1e-5)
  np.testing.assert_allclose(com, want.com, atol=1e-6)
  np.testing.assert_allclose(inertia, want.inertia, rtol=1e-4, atol=1e-6)


def test_convex_pieces_cut_only_bent_parts():
  box = trimesh.creation.box(extents=(0.5, 0.1, 0.1))
  assert len(tool_scene.convex_pieces(box)) == 1
  axe = tools.sample_tool(8, 0, "axe")
  handle = axe.parts[axe.names.index("handle")]
  assert handle.convex_hull.volume > 1.1 * handle.volume  # this handle is bent
  assert len(tool_scene.convex_pieces(handle)) == tool_scene.SLABS


def test_tools_simulate_and_render(tmp_path, monkeypatch):
  monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning log into the working directory
  tool = tools.sample_tool(3, 1)
  parts, _ = meshes.normalize(list(tool.parts))
  traj = tool_scene.simulate_tool(parts, tool.densities, steps=32)
  assert traj.shape == (4, 32, 7) and np.all(np.isfinite(traj))
  np.testing.assert_allclose(np.linalg.norm(traj[..., 3:], axis=-1), 1.0, atol=1e-6)
  with pytest.raises(RuntimeError, match="diverged"):
    tool_scene.simulate_tool(parts, tool.densities, ppdjax.default_pushes(1e7), steps=32)
  image = tool_scene.render_tool(parts, tool.materials, [0] * len(parts), height=64, width=64)
  empty = tool_scene.render_tool([trimesh.creation.box(extents=(0.01, 0.01, 0.01))
                                  .apply_translation([3.0, 3.0, 0.0])], ["wood"], [0],
                                 height=64, width=64)
  assert image.shape == (64, 64, 3) and image.dtype == np.uint8
  assert np.abs(image.astype(int) - empty).max(-1).astype(bool).sum() > 20  # the tool shows


def test_a_tools_dataset_is_written_and_read_as_towers_are(tmp_path):
  """Two tools, each under two density configurations (`data.configs_per_tool`), pushed at
  300 N (`data.tool_push_force`): the manifest records the pushes the trajectories had."""
  from ppdjax.configs import tiny
  from ppdjax.configs import tools as tools_preset
  from ppdjax.conventions import density_to_slot
  from ppdjax.dataset import generation, materials, storage, tool_generation
  # the preset pushes by volume about 2e3 N; data sections before the keys read 1e3 N alike
  assert tools_preset.get_config().data.tool_push == "by_volume"
  assert tool_generation.push_force({}) == tool_scene.TOOL_PUSH_FORCE
  config = tiny.get_config()
  config.data.update(kind="tools", num_tools=2, tools_per_shard=1, image_size=32, steps=12,
                     backend="mujoco", configs_per_tool=2, tool_push_force=300.0)
  for bad in (0.0, 2e4):
    data = config.data.copy_and_resolve_references()
    data.tool_push_force = bad
    with pytest.raises(ValueError, match="tool_push_force"):
      generation.check_config(data)
  manifest = generation.generate(config, str(tmp_path / "tools"), progress=False)
  assert manifest["kind"] == "tools" and manifest["tools"] == 2 and manifest["samples"] == 4
  assert "300 N" in manifest["engine"]["tools"]
  ds = storage.open_dataset(str(tmp_path / "tools"), verify=True)
  np.testing.assert_array_equal(ds.pushes.magnitudes, tool_scene.tool_pushes(300.0).magnitudes)
  batch = ds.take(np.arange(4))
  at_1e3 = tool_generation.tool_sample(config.seed, 0, 32, 12)["trajectories"]
  assert np.abs(batch["trajectories"][0] - at_1e3).max() > 1e-3  # a weaker push
  assert batch["trajectories"].shape == (4, 4, 12, 7) and batch["depth"].shape == (4, 32, 32)
  prims = batch["primitives"]
  for i in range(4):
    valid = prims.valid[i]
    assert 1 <= valid.sum() <= 5 and np.all((batch["materials"][i] >= 0) == valid)
    for m, rho in zip(batch["materials"][i][valid], prims.density[i][valid]):
      assert density_to_slot(rho) in materials.material_slots(materials.MATERIAL_NAMES[m])
  # a tool's configurations share its geometry, image and materials, not its densities
  np.testing.assert_array_equal(batch["tower_id"], [0, 0, 1, 1])
  for a in (0, 2):
    for field in ("voxels", "image", "materials"):
      np.testing.assert_array_equal(batch[field][a], batch[field][a + 1])
    np.testing.assert_array_equal(prims.half_size[a], prims.half_size[a + 1])
    assert not np.array_equal(prims.density[a], prims.density[a + 1])
    assert not np.array_equal(batch["trajectories"][a], batch["trajectories"][a + 1])
  # a sample is a pure function of (seed, index): the first configuration is the tool's own
  again = tool_generation.tool_sample(config.seed, 1, 32, 12, force=300.0)
  np.testing.assert_array_equal(again["trajectories"], batch["trajectories"][2])
  np.testing.assert_array_equal(again["half_size"], prims.half_size[2])
  own = tools.sample_tool(config.seed, 1).densities  # (its first attempt did not diverge)
  assert set(prims.density[2][prims.valid[2]].tolist()) <= set(own.astype(np.float32).tolist())


@pytest.mark.slow
def test_the_decompose_command_on_a_mesh_file(tiny_run, tmp_path):
  """`python -m ppdjax.decompose --mesh FILE --materials ...` end to end (tiny model)."""
  import json
  decompose = cli_module("ppdjax.decompose")
  tool = tools.sample_tool(3, 0, "hammer")
  scene = trimesh.Scene()
  for name, part in zip(tool.names, tool.parts):
    scene.add_geometry(part, node_name=name, geom_name=name)
  scene.export(tmp_path / "hammer.glb")
  record = decompose.run(str(tmp_path / "hammer.glb"), decompose._parse(
      "head=metal,handle=wood", number=False), None, tiny_run[0], str(tmp_path / "out"),
      {"samples": 2, "fit": False}, engine="box_plane")
  assert [p["material"] for p in record["parts"]] == ["wood", "metal"]
  assert 1 <= len(record["boxes"]) <= 5 and len(record["boxes_from_mesh"]) == 2
  assert (tmp_path / "out" / "decomposition.png").stat().st_size > 10_000
  written = json.loads((tmp_path / "out" / "decomposition.json").read_text())
  settings = written["settings"]  # the model's own, with the overrides
  assert settings["select"]["samples"] == 2 and settings["fit"]["enabled"] is False
  with pytest.raises(ValueError, match="name=value"):
    decompose._parse("head=metal,wood", number=False)


def test_pushes_by_volume_scale_with_the_tool_and_refuse_bad_values():
  """"by_volume": a tool twice the reference volume is pushed twice as hard (so tools of one
  mean density start alike); "fixed" ignores the volume."""
  ref = tool_scene.REFERENCE_VOLUME
  assert tool_scene.push_force_for(2e3, 2 * ref, "by_volume") == pytest.approx(4e3)
  assert tool_scene.push_force_for(2e3, 2 * ref, "fixed") == 2e3
  with pytest.raises(ValueError, match="push mode"):
    tool_scene.push_force_for(2e3, ref, "by_mass")
  with pytest.raises(ValueError, match="volume must be > 0"):
    tool_scene.push_force_for(2e3, float("nan"), "by_volume")
