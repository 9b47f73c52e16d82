"""Tools under the paper's protocol (dataset.tool_paper): the draw, the texturing, the body."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy import ndimage

from ppdjax import mass_properties, primitives, voxelize  # first: it sets MUJOCO_GL
from mujoco_reference import reference_model, reference_rollout
from ppdjax.configs import tools_paper
from ppdjax.dataset import generation, materials, storage, tool_paper, tool_scene
from ppdjax.dataset.mesh_boxes import _signed_distance
from ppdjax.conventions import density_to_slot
from conftest import cli_module


@pytest.fixture(scope="module")
def one_tool():
  """Tool 3 of seed 7 (a screwdriver: a grip, a shaft and a tip in two boxes) under 60
  configurations, at 32 px."""
  return tool_paper.tool_samples(7, 3, 32, 60)


def test_each_box_draws_its_material_uniformly_from_the_five(one_tool):
  valid = one_tool[0]["valid"]
  ids = np.concatenate([r["materials"][valid] for r in one_tool])
  assert set(ids.tolist()) <= set(range(len(materials.MATERIAL_NAMES)))
  counts = np.bincount(ids, minlength=5)
  expected = len(ids) / 5
  chi2 = ((counts - expected) ** 2 / expected).sum()
  assert chi2 < 18.5, counts  # chi-square, 4 degrees of freedom: p < 0.001 fails
  for r in one_tool:  # each density is a slot of its box's own material
    for k in np.flatnonzero(valid):
      name = materials.ALL_MATERIAL_NAMES[r["materials"][k]]
      assert int(density_to_slot(r["density"][k])) in materials.material_slots(name)
    assert (r["materials"][~valid] == -1).all()
  # a configuration is a pure function of (seed, index, c): made again with fewer
  # configurations, the first ones are the same arrays
  again = tool_paper.tool_samples(7, 3, 32, 2)
  for c, row in enumerate(again):
    for f, value in row.items():
      np.testing.assert_array_equal(value, one_tool[c][f], err_msg=f)


def test_the_recipe_stops_at_two_boxes_for_most_tools():
  from ppdjax.dataset import tools
  from ppdjax.dataset.meshes import normalize
  counts = [int(tool_paper.tool_boxes(normalize(list(tools.sample_tool(7, 0, c).parts))[0]
                                      ).valid.sum())
            for c in ("hammer", "axe", "screwdriver", "knife", "saw", "wrench")]
  assert max(counts) <= tool_paper.MAX_BOXES
  assert sum(c <= 2 for c in counts) >= 4, counts


def _two_boxes():
  """A bar and a post turned 0.4 rad about z, apart (as meshes), and the same two as
  Primitives."""
  turn = trimesh.transformations.rotation_matrix(0.4, (0, 0, 1))
  a = trimesh.creation.box(extents=(0.6, 0.1, 0.1))
  a.apply_translation((0.0, 0.0, -0.2))
  b = trimesh.creation.box(extents=(0.1, 0.1, 0.3))
  b.apply_transform(turn)
  b.apply_translation((0.3, 0.0, 0.0))
  quat = np.array([[1.0, 0.0, 0.0, 0.0], trimesh.transformations.quaternion_from_matrix(turn)])
  prims = primitives.make(np.array([[0.3, 0.05, 0.05], [0.05, 0.05, 0.15]]),
                          np.array([[0.0, 0.0, -0.2], [0.3, 0.0, 0.0]]), quat, density=1000.0)
  return [a, b], jax.tree.map(np.asarray, prims)


def test_every_face_is_textured_by_the_box_it_lies_in():
  parts, prims = _two_boxes()
  pieces, slots = tool_paper.box_meshes(parts, prims)
  assert slots == [0, 1]
  for piece, k in zip(pieces, slots):
    centres = piece.triangles_center
    rotation = np.asarray(primitives.quat_to_mat(prims.quat[k]))
    inside = _signed_distance(centres, (prims.pos[k], rotation, prims.half_size[k]))
    assert (inside <= 1e-6).all()
    assert piece.faces.max() < len(piece.vertices)
  assert sum(len(p.faces) for p in pieces) >= sum(len(p.faces) for p in parts)
  # changing one box's material changes the pixels of that box only
  wood, metal = "wood", "metal"
  images, _ = tool_scene.render_configs(
      pieces, [[wood, wood], [metal, wood], [wood, metal]], [[1, 1]] * 3, height=64, width=64)
  first = np.abs(images[1].astype(int) - images[0]).sum(-1) > 30
  second = np.abs(images[2].astype(int) - images[0]).sum(-1) > 30
  assert first.sum() > 20 and second.sum() > 20
  assert (first & second).sum() <= 0.05 * min(first.sum(), second.sum())


@pytest.fixture(scope="module")
def paper_dataset(tmp_path_factory):
  """Two tools x 2 configurations of the tiny paper-protocol preset, simulated by MuJoCo C."""
  config = tools_paper.get_config("tiny")
  config.data.num_tools = config.data.tools_per_shard = 2
  config.data.configs_per_tool = 2
  config.data.backend = "mujoco"
  config.data.steps = 64
  config.data.split_fractions = (0.0, 0.0, 1.0)
  out = str(tmp_path_factory.mktemp("tools_paper"))
  generation.generate(config, out, progress=False)
  return config, storage.open_dataset(out, "test")


def test_the_simulated_body_is_exactly_the_boxes(paper_dataset):
  config, data = paper_dataset
  assert len(data) == 4
  assert np.allclose(np.asarray(data.pushes.magnitudes), config.data.tool_push_force)
  for i in range(len(data)):
    s = data[i]
    prims = jax.tree.map(jnp.asarray, s["primitives"])
    model = reference_model(prims)  # what MuJoCo's compiler makes of the boxes
    mp = mass_properties(prims)
    assert float(mp.mass) == pytest.approx(float(model.body_mass[1]), rel=1e-5)
    assert np.allclose(np.asarray(mp.com), model.body_ipos[1], atol=1e-6)
    reference = reference_rollout(prims, data.pushes, steps=config.data.steps)
    assert np.abs(s["trajectories"] - reference).max() < 1e-4


def test_the_voxels_are_the_mesh_s_not_the_boxes(paper_dataset):
  _, data = paper_dataset
  s = data[0]
  box_voxels = np.asarray(voxelize(jax.tree.map(jnp.asarray, s["primitives"]))) > 0
  mesh_voxels = s["voxels"] > 0
  assert mesh_voxels.sum() < box_voxels.sum()  # the boxes hold air around the tool
  assert (mesh_voxels & ~ndimage.binary_dilation(box_voxels)).sum() == 0


@pytest.mark.slow
def test_the_decompose_command_observes_as_the_paper_protocol_model_was_trained(
    tiny_run, tmp_path):
  """`python -m ppdjax.decompose --mesh FILE --protocol=paper`: a model trained on the
  paper's protocol (here the tiny model, its data section marked so) sees the mesh's boxes
  as the body, and the record says which protocol it read."""
  import json
  import shutil
  decompose = cli_module("ppdjax.decompose")
  from ppdjax.dataset import tools
  model = str(tmp_path / "model")
  shutil.copytree(tiny_run[0], model)
  config = json.loads((tmp_path / "model" / "config.json").read_text())
  config["data"].update(tool_protocol="paper", tool_push_force=3e3)
  (tmp_path / "model" / "config.json").write_text(json.dumps(config))
  tool = tools.sample_tool(3, 0, "hammer")
  scene = trimesh.Scene()
  for name, part in zip(tool.names, tool.parts):
    scene.add_geometry(part, node_name=name, geom_name=name)
  scene.export(tmp_path / "hammer.glb")
  record = decompose.run(str(tmp_path / "hammer.glb"), {"head": "metal", "handle": "wood"},
                         None, model, str(tmp_path / "out"), {"samples": 2, "fit": False})
  assert record["protocol"] == "paper"
  truth = record["boxes_from_mesh"]  # the paper's boxes: a handle and a head
  assert len(truth) == 2
  # each box takes the density of the part it covers most: the handle's and the head's
  assert sorted(b["density"] for b in truth) == pytest.approx(
      sorted(p["density"] for p in record["parts"]))
  with pytest.raises(ValueError, match="protocol"):
    decompose.default_model(protocol="mesh")
