"""The README's demo: the shipped example, the physics tour and the smoke run's last steps."""

import json
import os

import pytest

from ppdjax import showcase
from ppdjax.configs import tiny

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.slow  # ~22 s on 2 cores (`make demo` runs it; test_physics pins the engines)
def test_physics_tour_writes_plot_and_summary(tmp_path):
  summary = showcase.physics_tour(tiny.get_config(), str(tmp_path))
  for name in ("trajectories.png", "summary.md", "summary.json"):
    assert os.path.getsize(tmp_path / name) > 100
  with open(tmp_path / "summary.json") as f:
    assert json.load(f)["mass_kg"] == summary["mass_kg"] > 0
  assert len(summary["speed_after_push_m_s"]) == 4
  assert all(0.05 < v < 10 for v in summary["speed_after_push_m_s"])
  assert max(summary["gap_to_reference_mm"]["first_0.1s_max"]) < 2.0


@pytest.mark.slow  # ~50 s on 2 cores (`make demo` runs it; test_assets pins the model)
def test_shipped_example_report_puts_the_answer_beside_the_truth(tmp_path):
  r = showcase.shipped_example(os.path.join(ROOT, "assets", "blocks_model"),
                               os.path.join(ROOT, "assets", "blocks_example.npz"),
                               str(tmp_path), samples=16, image_fit=False)
  assert os.path.getsize(tmp_path / "example.png") > 1000
  text = (tmp_path / "example.md").read_text()
  assert text.count("\n| ") == 1 + len(r["true_densities"])  # header + one row per box
  assert "Heaviest 2 boxes (numbered from the bottom): recovered" in text
  for d in r["true_densities"]:
    assert f"| {d:.0f} |" in text
  assert len(r["densities"]) == len(r["true_densities"]) == 4
  assert r["shape_matched"] >= 1 and 0 < r["distance_m"] < 0.5


@pytest.mark.slow  # ~60 s on 2 cores (`make demo` runs it; test_inference and test_assets
# pin evaluation and decompose)
def test_smoke_run_evaluates_and_decomposes(tiny_run, tiny_dataset, tmp_path):
  results = showcase.evaluate_and_decompose(tiny.get_config(), tiny_dataset, tiny_run[0],
                                            str(tmp_path))
  for name in ("decomposition.png", "eval/results.md", "eval/results.json", "eval/confusion.png"):
    assert os.path.getsize(tmp_path / name) > 100, name
  assert results["samples"] == tiny.get_config().eval.samples
  assert {"PPD", "PPD+Sample", "Oracle"} <= set(results["table2"])
