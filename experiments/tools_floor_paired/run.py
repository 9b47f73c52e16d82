"""The realistic tools model against the floor, paired on the floor's own test objects.

  python experiments/tools_floor_paired/run.py

The floor (`experiments/results/tools_realistic_floor/floor.json`) reads the first 48 test
tools of the preset's seed under their first 2 density configurations; the pipeline's
evaluation (`experiments/results/tools_realistic_run/eval_full.json`) keeps per-object
hits and squared errors for the whole test split (tools in id order, 8 configurations
each). This reads the model's rows on exactly the floor's objects and bootstraps the
differences over tools. Writes `experiments/results/tools_realistic_floor/paired.json`.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ppdjax.configs import tools
from ppdjax.dataset import storage
from ppdjax.metrics import bootstrap_interval

RESULTS = "experiments/results"


def test_tool_position() -> dict[int, int]:
  """Tool id -> its position among the test tools of the preset's split."""
  data = tools.get_config().data
  ids = np.arange(data.num_tools)
  test = ids[storage.split_of(ids, tuple(data.split_fractions)) == storage.SPLITS["test"]]
  return {int(t): k for k, t in enumerate(test)}


def paired(floor: dict, per_object: dict, configs_per_tool: int) -> dict:
  """Per row: both readers' top-1 and RMSE over the floor's boxes, and the model minus the
  floor with 95 % intervals over tools."""
  position = test_tool_position()
  configs = int(tools.get_config().floor.configs)  # the floor's configurations a tool
  out = {}
  for row, rec in per_object.items():
    # (floor hits, floor squared error, model hits, model squared error, boxes) per tool
    table = []
    for tool in floor["per_tool"]:
      true, mode = np.asarray(tool["true"]), np.asarray(tool["mode"])
      objects = [configs_per_tool * position[tool["index"]] + c for c in range(configs)]
      boxes = sum(rec["count"][o] for o in objects)
      if boxes != len(true):
        raise ValueError(f"tool {tool['index']}: {boxes} boxes in the evaluation, "
                         f"{len(true)} in the floor: the records are not of one split")
      table.append((np.sum(true == mode), np.sum((true - mode) ** 2.0),
                    sum(rec["top1"][o] for o in objects),
                    sum(rec["sq_err"][o] for o in objects), boxes))
    table = np.asarray(table, float)

    def scores(i):
      t = table[i]
      n = t[:, 4].sum()
      return (100 * t[:, 0].sum() / n, np.sqrt(t[:, 1].sum() / n),
              100 * t[:, 2].sum() / n, np.sqrt(t[:, 3].sum() / n))

    everything = np.arange(len(table))
    f_top1, f_rmse, m_top1, m_rmse = scores(everything)
    out[row] = {
        "tools": len(table), "boxes": int(table[:, 4].sum()),
        "floor": {"top1": f_top1, "rmse": f_rmse}, "model": {"top1": m_top1, "rmse": m_rmse},
        "top1_difference": m_top1 - f_top1,
        "top1_difference_ci95": list(bootstrap_interval(
            lambda i: scores(i)[2] - scores(i)[0], len(table), resamples=4000)),
        "rmse_difference": m_rmse - f_rmse,
        "rmse_difference_ci95": list(bootstrap_interval(
            lambda i: scores(i)[3] - scores(i)[1], len(table), resamples=4000)),
    }
  return out


def main():
  with open(os.path.join(RESULTS, "tools_realistic_floor", "floor.json")) as f:
    floor = json.load(f)
  with open(os.path.join(RESULTS, "tools_realistic_run", "eval_full.json")) as f:
    evaluation = json.load(f)
  per_tool = evaluation["objects"] // evaluation["geometries"]
  result = {"command": "python experiments/tools_floor_paired/run.py",
            "rows": paired(floor, evaluation["per_object"], per_tool)}
  path = os.path.join(RESULTS, "tools_realistic_floor", "paired.json")
  with open(path, "w") as f:
    json.dump(result, f, indent=1)
  for row, r in result["rows"].items():
    print(f"{row}: {r['model']['top1']:.1f} / {r['model']['rmse']:.2f} against the floor's "
          f"{r['floor']['top1']:.1f} / {r['floor']['rmse']:.2f} on {r['boxes']} boxes of "
          f"{r['tools']} tools; top-1 {r['top1_difference']:+.1f} "
          f"[{r['top1_difference_ci95'][0]:+.1f}, {r['top1_difference_ci95'][1]:+.1f}], RMSE "
          f"{r['rmse_difference']:+.2f} [{r['rmse_difference_ci95'][0]:+.2f}, "
          f"{r['rmse_difference_ci95'][1]:+.2f}]")
  print("->", path)


if __name__ == "__main__":
  main()
