"""The README's demo on the tiny preset."""

import json
import os

from ppdjax import demo
from ppdjax.configs import tiny


def test_demo_writes_plot_and_summary(tmp_path):
  summary = demo.run_demo(tiny.get_config(), str(tmp_path))
  for name in ("trajectories.png", "summary.md", "summary.json"):
    assert os.path.getsize(tmp_path / name) > 100
  with open(tmp_path / "summary.json") as f:
    assert json.load(f)["mass_kg"] == summary["mass_kg"] > 0
  assert len(summary["speed_after_push_m_s"]) == 4
  assert all(0.05 < v < 10 for v in summary["speed_after_push_m_s"])
  assert max(summary["gap_to_reference_mm"]["first_0.1s_max"]) < 2.0


def test_demo_evaluates_and_decomposes(tiny_run, tiny_dataset, tmp_path):
  results = demo.run_evaluation(tiny.get_config(), tiny_dataset, tiny_run[0], str(tmp_path))
  for name in ("decomposition.png", "eval/results.md", "eval/results.json", "eval/confusion.png"):
    assert os.path.getsize(tmp_path / name) > 100, name
  assert results["samples"] == tiny.get_config().eval.samples
  assert {"PPD", "PPD+Sample", "Oracle"} <= set(results["table2"])
