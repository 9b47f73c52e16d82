"""The realistic tools benchmark's floor (ppdjax.eval.tool_floor): its pieces on hand cases."""

import numpy as np
import pytest

import ppdjax  # noqa: F401  (MuJoCo's GL setting before mujoco is imported)
from ppdjax.configs import tools as tools_preset
from ppdjax.dataset import tool_scene, tools
from ppdjax.dataset.meshes import normalize, voxelize_parts
from ppdjax.eval import tool_floor


def test_the_builder_replays_the_tools_geometry_and_the_chain_keeps_the_voxels():
  """Replayed with its own draws a builder gives the tool's meshes; every geometry sample
  has exactly the observed voxels, and dimensions the voxels cannot see move."""
  category, draws = tool_floor.builder_draws(0, 2)  # a saw: a blade 1-2 mm thick
  tool = tools.sample_tool(0, 2)
  parts, _ = normalize(list(tool.parts))
  values = [v for kind, _, _, v in draws if kind == "uniform"]
  replayed = tool_floor.parts_of(category, draws, values)
  assert category == tool.category == "saw"
  for a, b in zip(replayed, parts):
    np.testing.assert_allclose(a.vertices, b.vertices)
  voxels = voxelize_parts(parts)[0]
  samples = tool_floor.geometry_samples(category, draws, voxels, 3, np.random.default_rng(0),
                                       sweeps=1)
  for sample in samples:
    assert np.array_equal(voxelize_parts(sample)[0], voxels)
  volumes = {round(float(sum(abs(p.volume) for p in s)), 9) for s in samples}
  assert len(volumes) > 1  # the hidden dimensions moved


def test_mass_properties_round_trip_and_match_the_simulators():
  """θ of a tool's pieces at their densities is the body `tool_scene` simulates; θ maps
  back to that mass, centre and inertia."""
  tool = tools.sample_plausible_tool(0, 1)
  parts, _ = normalize(list(tool.parts))
  mass, com, inertia = tool_scene.mass_properties(parts, tool.densities)
  pieces = np.asarray(tool.pieces)
  rho = tool.densities[[int(np.flatnonzero(pieces == q)[0]) for q in range(tool.num_pieces)]]
  theta = tool_floor.thetas(tool_floor.piece_terms(parts, tool.pieces), rho[None])[0]
  m, c, i = tool_floor._inertial(theta)  # pylint: disable=protected-access
  assert m == pytest.approx(mass) and np.allclose(c, com)
  np.testing.assert_allclose(i, inertia, rtol=1e-6, atol=1e-12)


def test_a_sharp_reading_on_the_true_geometry_finds_the_slots():
  """With the true geometry alone and much information, the posterior's mode is the true
  slot of each piece; with none, it is the prior's."""
  tool = tools.sample_plausible_tool(0, 4)  # a spatula: handle and blade
  parts, _ = normalize(list(tool.parts))
  pieces = np.asarray(tool.pieces)
  first = [int(np.flatnonzero(pieces == q)[0]) for q in range(tool.num_pieces)]
  theta = tool_floor.thetas(tool_floor.piece_terms(parts, tool.pieces),
                            tool.densities[first][None])[0]
  sets = tool_floor.piece_sets(tool)
  mode, mean = tool_floor.read_tool([parts], tool.pieces, sets, theta, np.eye(10) * 1e10,
                                    np.random.default_rng(0))
  np.testing.assert_array_equal(mode, np.asarray(tool.slots)[first])
  np.testing.assert_allclose(mean, np.asarray(tool.slots)[first], atol=0.5)
  assert tool_floor.slot_prior(("wood",))[:10].sum() == pytest.approx(1.0)


@pytest.mark.slow  # two test tools read: about a minute on 2 cores
def test_the_floor_of_the_tiny_preset_scores_its_boxes():
  config = tools_preset.get_config("tiny")
  result = tool_floor.compute(config, progress=False)
  assert result["tools"] == config.floor.tools and result["boxes"] >= 2
  assert 0 <= result["top1"] <= 100 and result["rmse"] >= 0
  assert sum(v["boxes"] for v in result["by_material"].values()) == result["boxes"]
