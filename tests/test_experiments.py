"""python -m ppdjax.reproduce blocks|tools: the step list, and (slow) the pipelines on tiny
presets; the studies that still run (experiments/<study>/run.py)."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ppdjax.dataset import tools

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = ["--config=ppdjax/configs/tiny.py", "--config.train.geometry_steps=10",
        "--config.train.joint_steps=10", "--config.train.eval_every=10", "--max_objects=4",
        "--nojoint", "--notrue_shapes"]  # +Joint compiles for minutes on a CPU


def _blocks(*args, timeout=120):
  env = {**os.environ, "JAX_PLATFORMS": "cpu",
         "JAX_COMPILATION_CACHE_DIR": os.path.join(ROOT, ".jax_cache")}
  return subprocess.run([sys.executable, "-m", "ppdjax.reproduce", "blocks", *args], cwd=ROOT,
                        env=env,
                        capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow  # ~13 s on 2 cores: `make test-all`
def test_list_shows_every_step_and_bad_steps_are_named(tmp_path):
  done = _blocks(*TINY, f"--root={tmp_path}", "--list")
  assert done.returncode == 0, done.stderr[-2000:]
  names = [line.split()[1] for line in done.stdout.splitlines() if line.startswith("todo")]
  assert names == ["generate", "compile:full", "train:full", "evaluate:full", "export",
                   "train:no_image",
                   "evaluate:no_image", "train:no_trajectory", "evaluate:no_trajectory",
                   "train:no_voxels", "evaluate:no_voxels", "train:rgbd", "evaluate:rgbd",
                   "report"]
  streamed = _blocks(*TINY, "--config.train.stream_steps=5", f"--root={tmp_path}", "--list")
  assert [line.split()[1] for line in streamed.stdout.splitlines()[:3]] == [
      "generate", "compile:full", "train:geometry"], streamed.stdout
  bad = _blocks(*TINY, f"--root={tmp_path}", "--step=train")
  assert bad.returncode != 0 and "--step must be" in bad.stderr


@pytest.mark.slow  # about 6 minutes on 2 cores
def test_tiny_pipeline_runs_step_by_step_and_reports(tmp_path):
  root, results, assets = (str(tmp_path / d) for d in ("root", "results", "assets"))
  args = [*TINY, f"--root={root}", f"--results={results}", f"--assets={assets}"]
  for _ in range(15):  # one step per call, as an interrupted user would go on
    done = _blocks(*args, "--step=next", timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    if os.path.exists(os.path.join(results, "blocks.json")):
      break
  with open(os.path.join(results, "blocks.json")) as f:
    r = json.load(f)
  assert set(r["table2"]) >= {"Frequent", "Nearest", "Oracle", "PPD (no trajectory)",
                              "PPD (no image)", "PPD (no voxels)", "PPD (RGB-D)", "PPD (full)",
                              "PPD (full)+Sample"}
  assert all(set(row) >= {"top1", "top5", "top10", "rmse", "mae", "ci95", "objects"}
             for row in r["table2"].values())
  assert "f1" in r and r["table4"] and r["table5"] and r["steps"]["generate"]["calls"] == 1
  for name in ("blocks.md", "blocks_learning_curves.png", "blocks_confusion.png",
               "blocks_decomposition.png"):
    assert os.path.exists(os.path.join(results, name)), name
  assert os.path.exists(os.path.join(assets, "blocks_model", "export.json"))
  kept = os.path.join(root, "full", "eval_partial")  # the full model's records, compacted
  assert sorted(os.listdir(kept)) == ["records.npz", "settings.json"]
  logs = sorted(os.listdir(os.path.join(results, "blocks_runs")))
  assert logs == ["data_card.md", "full.metrics.jsonl", "no_image.metrics.jsonl",
                  "no_trajectory.metrics.jsonl", "no_voxels.metrics.jsonl", "rgbd.metrics.jsonl",
                  "steps.jsonl"]
  listed = _blocks(*args, "--list")
  assert listed.stdout.count("done") == 13  # every step but the report (rerun each time)


_FAKE_STEP = """
import os, sys, time
step = [a for a in sys.argv if a.startswith("--step=")][-1][len("--step="):]
root = sys.argv[1]
with open(os.path.join(root, "order"), "a") as f:
  f.write(f"start {step}\\n")
time.sleep(5.0 if step.startswith("slow") else 0.3)
if step == "bad":
  sys.exit(2)
if step.startswith("hungry") and not os.path.exists(os.path.join(root, step + ".tried")):
  open(os.path.join(root, step + ".tried"), "w").close()
  print("jax.errors.JaxRuntimeError: RESOURCE_EXHAUSTED: Out of memory")
  sys.exit(1)
with open(os.path.join(root, "order"), "a") as f:
  f.write(f"end {step}\\n")
open(os.path.join(root, step), "w").close()
"""


def test_jobs_start_steps_when_their_inputs_are_done_and_stop_behind_a_failure(tmp_path,
                                                                              capsys):
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.reproduce import steps as pipeline_steps
  script = tmp_path / "step.py"
  script.write_text(_FAKE_STEP)
  needs = {"a": (), "b": ("a",), "c": ("a",), "d": ("b", "c"), "bad": (), "e": ("bad",)}
  done = lambda n: os.path.exists(tmp_path / n)
  rc = pipeline_steps.run_side_by_side(list(needs), needs.__getitem__, done, 2,
                                       [str(script), str(tmp_path)], str(tmp_path / "logs"))
  assert rc == 1  # "bad" failed, so "e" never started
  lines = (tmp_path / "order").read_text().split("\n")
  started = [line.split()[1] for line in lines if line.startswith("start")]
  assert set(started) == {"a", "b", "c", "d", "bad"}
  for step, inputs in needs.items():
    if step in started:
      assert all(lines.index(f"end {i}") < lines.index(f"start {step}") for i in inputs), step
  assert not done("e") and done("d")
  said = capsys.readouterr().out
  assert "-- bad: FAILED (exit 2)" in said and "-- e: not started (bad failed)" in said
  again = pipeline_steps.run_side_by_side(["a", "b"], needs.__getitem__, done, 2,
                                          [str(script), str(tmp_path)], str(tmp_path / "logs"))
  assert again == 0 and started == [ln.split()[1] for ln in
                                    (tmp_path / "order").read_text().split("\n")
                                    if ln.startswith("start")]  # done steps are not rerun


def test_a_step_out_of_memory_beside_others_starts_again_when_fewer_run(tmp_path, capsys):
  """Out of accelerator memory beside another step: retried once that step has ended;
  out of memory alone: a failure."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.reproduce import steps as pipeline_steps
  script = tmp_path / "step.py"
  script.write_text(_FAKE_STEP)
  needs = {"slow": (), "hungry": ()}
  done = lambda n: os.path.exists(tmp_path / n)
  rc = pipeline_steps.run_side_by_side(list(needs), needs.__getitem__, done, 2,
                                       [str(script), str(tmp_path)], str(tmp_path / "logs"))
  lines = (tmp_path / "order").read_text().split("\n")
  assert rc == 0 and done("hungry") and lines.count("start hungry") == 2
  assert lines.index("end slow") < len(lines) - 1 - lines[::-1].index("start hungry")
  assert "hungry: out of accelerator memory" in capsys.readouterr().out
  assert "RESOURCE_EXHAUSTED" in (tmp_path / "logs" / "hungry.log").read_text()  # kept
  alone = pipeline_steps.run_side_by_side(["hungry2"], lambda n: (), done, 2,
                                          [str(script), str(tmp_path)], str(tmp_path / "logs"))
  assert alone == 1 and "-- hungry2: FAILED" in capsys.readouterr().out


def test_light_steps_run_beside_the_jobs(tmp_path):
  """A light step (compiling ahead, no accelerator) starts beside a full set of jobs, and
  holds a job's place while it runs: no other step starts beside it then."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.reproduce import steps as pipeline_steps
  script = tmp_path / "step.py"
  script.write_text(_FAKE_STEP)
  needs = {"a": (), "b": (), "slow_light": ()}
  rc = pipeline_steps.run_side_by_side(list(needs), needs.__getitem__,
                                       lambda n: os.path.exists(tmp_path / n), 1,
                                       [str(script), str(tmp_path)], str(tmp_path / "logs"),
                                       light=lambda n: n == "slow_light")
  lines = (tmp_path / "order").read_text().split("\n")
  assert rc == 0 and lines.index("start slow_light") < lines.index("end a")  # beside "a"
  assert lines.index("end a") < lines.index("start b")  # one job at a time
  assert lines.index("end slow_light") < lines.index("start b")  # light holds a job's place


@pytest.mark.slow  # about 5 minutes on 2 cores
def test_tools_pipeline_runs_and_reports_table3(tmp_path):
  """ppdjax.reproduce tools on the tools preset's tiny size (the realistic benchmark: labels
  by physical piece, pushes by volume): every step, two at a time as their inputs allow,
  then the report with its breakdowns by material and category."""
  root, results, assets = (str(tmp_path / d) for d in ("root", "results", "assets"))
  env = {**os.environ, "JAX_PLATFORMS": "cpu",
         "JAX_COMPILATION_CACHE_DIR": os.path.join(ROOT, ".jax_cache")}
  run = subprocess.run([sys.executable, "-m", "ppdjax.reproduce", "tools",
                        "--config=ppdjax/configs/tools.py:tiny", f"--root={root}",
                        f"--results={results}", f"--assets={assets}", "--jobs=2"], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=900)
  assert run.returncode == 0, run.stderr[-3000:]
  with open(os.path.join(results, "tools_realistic.json")) as f:
    table = json.load(f)
  assert list(table["table3"])[:7] == ["Frequent", "Nearest", "Oracle", "PPD (no trajectory)",
                                       "PPD (no image)", "PPD (full)", "PPD (full)+Sample"]
  assert table["objects"] >= 1 and "f1" in table["shape"] and table["commit"]
  assert "train:pretrain" in table["steps"] and table["wall_seconds"] > 0
  # the breakdowns: boxes by material add up to the headline row's; categories recorded
  boxes = sum(v["boxes"] for v in table["by_material"].values())
  top1 = sum(v["boxes"] * v["top1"] for v in table["by_material"].values()) / boxes
  assert top1 == pytest.approx(table["table3"]["PPD (full)+Sample"]["top1"])
  assert set(table["by_material"]) <= {"wood", "stone", "ceramic", "metal"}  # never brick
  assert 0 <= table["metal_range_confusions"] <= 100
  assert set(table["by_category"]["PPD (full)"]) <= set(tools.CATEGORIES)
  assert table["push"] == "by_volume" and table["speeds"]["percentiles"]["p50"] > 0
  assert 0 <= table["floor"]["top1"] <= 100 and table["floor"]["boxes"] >= 1
  text = open(os.path.join(results, "tools_realistic.md")).read()
  assert "## By material" in text and "## By category" in text and "start" in text
  assert "## The floor" in text
  assert os.path.exists(os.path.join(results, "tools_realistic_decomposition.png"))
  assert os.path.exists(os.path.join(results, "tools_realistic_learning_curves.png"))
  assert os.path.exists(os.path.join(assets, "tools_model", "config.json"))
  from ppdjax.eval import partial  # pylint: disable=import-outside-toplevel
  kept = os.path.join(root, "full", "eval", "partial")  # the full model's records, compacted
  assert sorted(os.listdir(kept)) == ["records.npz", "settings.json"]
  assert len(partial.saved_records(kept)[("blocks",)]) == table["objects"]
  listed = subprocess.run([sys.executable, "-m", "ppdjax.reproduce", "tools", "--list",
                           "--config=ppdjax/configs/tools.py:tiny", f"--root={root}"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
  states = [line.split()[0] for line in listed.stdout.splitlines()]
  assert states == ["done"] * 10 + ["todo"], listed.stdout  # the report always runs again


def test_step_log_counts_overlapping_calls_once(tmp_path):
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.reproduce import steps as pipeline_steps
  rows = [{"step": "a", "seconds": 10.0, "start": 0.0, "end": 10.0, "device": "cpu"},
          {"step": "b", "seconds": 10.0, "start": 5.0, "end": 15.0, "device": "cpu"},
          {"step": "a", "seconds": 4.0, "start": 20.0, "end": 24.0, "device": "cpu"},
          {"step": "old", "seconds": 3.0, "device": "cpu"}]  # no start/end: counts itself
  (tmp_path / "steps.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
  log = pipeline_steps.read_log(str(tmp_path))
  assert log["steps"]["a"] == {"seconds": 14.0, "calls": 2, "device": "cpu"}
  assert log["total_seconds"] == 27.0 and log["wall_seconds"] == 22.0
  assert "| a | 2 | 14 | cpu |" in pipeline_steps.steps_md(log)
  assert pipeline_steps.read_log(str(tmp_path / "none"))["steps"] == {}


def test_a_call_that_raises_is_logged_unfinished(tmp_path):
  """A step's crashed call (e.g. out of accelerator memory) still counts its time."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.reproduce import steps as pipeline_steps

  def crash():
    raise RuntimeError("RESOURCE_EXHAUSTED")

  with pytest.raises(RuntimeError, match="RESOURCE_EXHAUSTED"):
    pipeline_steps.run_step(str(tmp_path), "train:x", lambda: False, crash)
  rows = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
  assert [(r["step"], r["finished"]) for r in rows] == [("train:x", False)]
  assert pipeline_steps.read_log(str(tmp_path))["steps"]["train:x"]["calls"] == 1


@pytest.mark.slow  # a finished study's script (~18 s on 2 cores): `make test-all`
def test_the_whole_split_joins_blocks_json_and_the_targets_read_it(tmp_path):
  """blocks_whole_split.py on the committed run's files: the targets then read the whole
  split's rows; an evaluation of a few objects is refused."""
  results = os.path.join(ROOT, "experiments", "results")
  with open(os.path.join(results, "blocks.json")) as f:
    blocks = json.load(f)
  blocks.pop("whole_split", None)
  (tmp_path / "res").mkdir()
  (tmp_path / "res" / "blocks.json").write_text(json.dumps(blocks))
  ev = os.path.join(results, "blocks_whole_split")
  run = lambda d: subprocess.run(
      [sys.executable, "experiments/blocks_whole_split/run.py", f"--eval={d}",
       f"--results={tmp_path / 'res'}", "--machine=test"], cwd=ROOT, capture_output=True,
      text=True, timeout=120, env={**os.environ, "JAX_PLATFORMS": "cpu"})
  done = run(ev)
  assert done.returncode == 0, done.stderr[-2000:]
  with open(tmp_path / "res" / "blocks.json") as f:
    joined = json.load(f)
  with open(os.path.join(ev, "results.json")) as f:
    full = json.load(f)
  row = joined["whole_split"]["table2"]["PPD (full)+Fit+Sample+Refine"]
  assert row["objects"] == full["objects"] == 4800
  assert row["top1"] == full["table2"]["PPD+Fit+Sample+Refine"]["top1"]
  md = (tmp_path / "res" / "blocks.md").read_text()
  assert f"| PPD (full)+Fit+Sample+Refine top-1 | {row['top1']:.2f} |" in md
  assert (tmp_path / "res" / "blocks_whole_split" / "results.md").exists()
  small = tmp_path / "small"
  small.mkdir()
  (small / "results.json").write_text(json.dumps({**full, "objects": 64}))
  refused = run(small)
  assert refused.returncode != 0 and "not the whole test split" in refused.stderr


@pytest.mark.slow  # a finished study's script (~22 s on 2 cores): `make test-all`
def test_tool_shape_errors_find_the_attribute_that_misses():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  import numpy as np
  from ppdjax.primitives import Primitives
  from tool_shape_errors import run as tool_shape_errors  # pylint: disable=import-outside-toplevel

  # two tools of two boxes each: a bar along x and a thin plate beside it
  half = np.array([[[0.3, 0.05, 0.04], [0.1, 0.08, 0.01]]] * 2, np.float32)
  pos = np.array([[[-0.15, 0.0, 0.0], [0.3, 0.0, 0.0]]] * 2, np.float32)
  quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (2, 2, 1))
  true = Primitives(half, pos, quat, np.full((2, 2), 500.0, np.float32), np.ones((2, 2), bool))
  same = tool_shape_errors.analyse(true, true)
  assert same["f1"] == 100.0 and same["matched"] == 100.0 and same["count_exact"] == 100.0
  assert same["errors"]["centre_voxels"]["median"] == 0.0
  # the second tool's bar is 4 voxels off along y: only the centre swap brings it back
  shifted = pos.copy()
  shifted[1, 0, 1] += 4 / 32
  moved = true.replace(pos=shifted)
  out = tool_shape_errors.analyse(moved, true)
  assert out["matched"] == 75.0 and out["f1"] == 75.0
  assert out["matched_with_true"]["centre"] == 100.0
  assert out["matched_with_true"]["sizes"] == 75.0
  assert out["by_thinnest_side"]["0-1 voxels"]["matched"] == 100.0  # the plates (0.6 voxel)
  assert out["by_thinnest_side"]["2-4 voxels"]["matched"] == 50.0  # the bars (2.6 voxels)


@pytest.mark.slow  # a finished study's script (~15 s on 2 cores): `make test-all`
def test_tools_rerun_replaces_the_full_models_rows_and_keeps_the_ablations(tmp_path):
  """experiments/tools_rerun/run.py on the committed results (the shipped run's own evaluation
  of the full model, marked): the full model's rows and the τ sweep come from the new
  evaluation; the ablations' rows and the run's steps stay; an evaluation over other
  objects is refused."""
  results = os.path.join(ROOT, "experiments", "results")
  shutil.copy(os.path.join(results, "tools.json"), tmp_path / "tools.json")
  new = tmp_path / "eval"
  shutil.copytree(os.path.join(results, "tools_runs", "eval_full"), new)
  with open(new / "results.json") as f:
    ev = json.load(f)
  ev["table2"]["PPD+Sample"]["top1"] = 99.0  # a marker that must reach tools.json
  with open(new / "results.json", "w") as f:
    json.dump(ev, f)
  env = {**os.environ, "PYTHONPATH": os.path.join(ROOT, "experiments")}
  run = lambda: subprocess.run(  # noqa: E731
      [sys.executable, "experiments/tools_rerun/run.py", f"--eval={new}", f"--results={tmp_path}",
       "--machine=test"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
  done = run()
  assert done.returncode == 0, done.stderr[-2000:]
  with open(tmp_path / "tools.json") as f:
    r = json.load(f)
  with open(os.path.join(results, "tools.json")) as f:
    before = json.load(f)
  assert r["rows"]["PPD (full)+Sample"]["top1"] == 99.0
  assert r["rows"]["PPD (no image)"] == before["rows"]["PPD (no image)"]
  assert r["steps"] == before["steps"] and r["rerun"]["machine"] == "test"
  md = (tmp_path / "tools.md").read_text()
  assert "| 99.0 [" in md and "τ on the test tools" in md
  ev["objects"] = 12
  with open(new / "results.json", "w") as f:
    json.dump(ev, f)
  refused = run()
  assert refused.returncode != 0 and "test tools" in refused.stderr


def test_table5_errors_reads_saved_records_and_finds_the_tail(tmp_path):
  """Twenty 2-block objects in two saved batches, one of them 10 slots off: it holds all
  of the squared error; padded boxes' NaN faces are skipped. (Run as a command: its flags
  would clash with other modules' in this process.)"""
  from ppdjax.eval import partial
  store = partial.PartialRecords(str(tmp_path / "partial"), {"test": 1})
  valid = np.zeros((10, 5), bool)
  valid[:, :2] = True
  faces = np.where(valid[..., None], 0.001, np.nan) * np.ones((10, 5, 6))
  for start in (0, 10):
    guess = np.full((10, 5), 3)
    if start:
      guess[0, 0] = 13
    store.save(start, {("blocks",): valid.sum(-1), ("true_slot",): np.where(valid, 3, -1),
                       ("true_valid",): valid, ("guess", "R"): guess, ("faces", "fit"): faces})
  run = subprocess.run([sys.executable, "experiments/table5_errors/run.py", f"--eval={tmp_path}",
                        "--row=R", "--faces=fit", f"--out={tmp_path / 'out.json'}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
  assert run.returncode == 0, run.stderr[-2000:]
  out = json.loads((tmp_path / "out.json").read_text())["by_blocks"]["2"]
  assert out["objects"] == 20 and out["share_worst_5pct"] == 1.0
  assert out["rmse"] == pytest.approx(np.sqrt(100 / 40)) and out["rmse_without_worst_5pct"] == 0
  assert out["objects_off_by_more_than_5_slots"] == pytest.approx(0.05)
  assert out["worst_face_mm_median"] == pytest.approx(1.0)


@pytest.mark.slow  # a tool simulated six times by MuJoCo C, a few seconds
def test_tool_identifiability_measures_the_parts_and_the_box_mismatch():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from tool_identifiability import run as tool_identifiability  # pylint: disable=import-outside-toplevel

  assert tool_identifiability.other_metal_mode(25) == 84
  assert tool_identifiability.other_metal_mode(90) == 27
  a = np.zeros((4, 10, 7))
  b = a.copy()
  b[..., 1] = 0.003  # 3 mm along y at every step
  assert tool_identifiability.distance_mm(a, b) == pytest.approx(3.0)
  tool = tools.sample_tool(2026, 0, category="hammer")
  r = tool_identifiability.study_tool(tool)
  assert r["category"] == "hammer" and len(r["parts"]) == len(tool.parts)
  assert r["mismatch_mm"] > 0 and r["moved_mm"] > 0
  assert r["box_mass_ratio"] > 1  # boxes cover more than the parts
  assert r["mass_part_mm"] > 0 and r["shape_part_mm"] > 0
  assert sum(p["mass_fraction"] for p in r["parts"]) == pytest.approx(1.0)
  for p in r["parts"]:  # a heavier part changes the motion, and metal has its other mode
    assert p["x1.5"] > 0 and p["x0.667"] > 0
    assert ("metal mode" in p) == (p["material"] == "metal")
  summary = tool_identifiability.summarize([r])
  assert summary["tools"] == 1 and summary["parts"] == len(tool.parts)


@pytest.mark.slow  # one tool, 3 x 8 candidates by MuJoCo C, a few seconds
def test_tool_mass_calibration_picks_among_candidates_that_hold_the_labels():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from tool_mass_calibration import run as study  # pylint: disable=import-outside-toplevel

  labels, valid = np.array([10, 50, 0, 0, 0]), np.array([True, True, False, False, False])
  slots = study.candidate_slots(labels, valid, 64, 20, np.random.default_rng(0))
  np.testing.assert_array_equal(slots[0], labels)  # the truth is always a candidate
  assert np.all(slots[:, 2:] == 0) and np.all(np.abs(slots[:, :2] - labels[:2]) <= 20)
  assert slots.min() >= 0 and len({tuple(s) for s in slots}) > 32
  tool = tools.sample_tool(2026, 0, category="hammer")
  r = study.study_tool(tool, 1.3, 8, 5, np.random.default_rng(0))
  assert r["box_mass_ratio"] > 1 and len(r["labels"]) >= 1
  for name in study.FACTORS:  # the pick is the closest, so no further than the labels
    assert r[name]["distance_mm"] <= r[name]["truth_distance_mm"] + 1e-9
    assert len(r[name]["slots"]) == len(r["labels"])
  s = study.summarize([r, r])
  assert s["tools"] == 2 and s["boxes"] == 2 * len(r["labels"])
  for name in study.FACTORS:
    lo, hi = s["rows"][name]["rmse_ci95"]
    assert lo <= s["rows"][name]["rmse"] + 1e-9 and s["rows"][name]["rmse"] <= hi + 1e-9


@pytest.mark.slow  # one tool, three bodies by MuJoCo C, a few seconds
def test_tool_voxel_body_covers_each_voxel_once_and_is_simulated():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from tool_voxel_body import run as study  # pylint: disable=import-outside-toplevel

  per_part = np.zeros((2, 32, 32, 32), bool)
  per_part[0, 3, 4, 2:9] = True  # one run
  per_part[0, 3, 4, 12] = True  # a second run in the same column
  per_part[1, 3, 4, 5:15] = True  # overlaps part 0: voxels 5-8 stay part 0's
  per_part[1, 10, 10, 0] = True
  boxes = study.voxel_columns(per_part)
  volume = sum(np.prod(hi - lo) for _, lo, hi in boxes)
  assert volume * 32 ** 3 == pytest.approx(per_part.any(0).sum())
  assert sorted((p, round(lo[2] * 32 + 16), round(hi[2] * 32 + 16)) for p, lo, hi in boxes) == [
      (0, 2, 9), (0, 12, 13), (1, 0, 1), (1, 9, 12), (1, 13, 15)]
  r = study.study_tool(tools.sample_tool(2026, 0, category="hammer"))
  assert r["voxel_boxes"] > 0 and r["voxel_mass_ratio"] > 0 and r["moved_mm"] > 0
  assert all(r[name] > 0 for name in study.BODIES)
  s = study.summarize([r])
  assert s["tools"] == 1 and s["by_category"]["hammer"]["tools"] == 1


@pytest.mark.slow  # one tool and one tower, a few dozen MuJoCo C rollouts
def test_tool_resolution_separates_what_other_parts_can_mimic():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from tool_resolution import run as study  # pylint: disable=import-outside-toplevel

  # two columns that are the same motion: neither is unique; a third apart is
  jac = np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
  np.testing.assert_allclose(study.unique_sensitivity(jac), [0.0, 0.0, 3.0], atol=1e-9)
  a = np.zeros((4, 10, 7))
  a[..., 3] = 1.0
  b = a.copy()
  b[..., 1] = 0.003  # 3 mm along y at every step: RMS 3 mm
  assert np.linalg.norm(study.features_mm(b) - study.features_mm(a)) == pytest.approx(3.0)
  tool = tools.sample_tool(2026, 0, category="hammer")
  r = study.study_tool(tool, 1e3)
  assert r["category"] == "hammer" and len(r["parts"]) == len(tool.parts) and r["moved_mm"] > 0
  for p in r["parts"]:
    assert 0 <= p["unique_mm"] <= p["alone_mm"] + 1e-9 and p["voxel_volume_ratio"] > 1
    assert p["resolution_slots_1mm"] == pytest.approx(10 * p["resolution_slots_0.1mm"])
  curve = study.tool_curve(tool, 1e3)  # the changes, the ±5 % mismatch, the motion
  n = len(study.CURVE_STEPS)
  assert len(curve) == n + 2 and curve[n - 1] > curve[0] >= 0
  assert 0 <= curve[n] <= 1 and curve[n + 1] > 0
  towers = study.tower_curves(0, 1)
  assert len(towers) == 1 and towers[0][n - 1] > towers[0][0] >= 0 and towers[0][n + 1] > 0
  summary = study.summarize([r])
  assert sum(summary[f"hammer {name}"]["parts"] for name in tool.names) == len(tool.parts)


@pytest.mark.slow  # one tool, 2 x 2 x 5 candidates by MuJoCo C, a few seconds
def test_tool_push_study_picks_the_truth_when_it_is_a_candidate():
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from ppdjax.dataset.materials import material_slots
  from tool_push_study import run as study  # pylint: disable=import-outside-toplevel

  tool = tools.sample_tool(2026, 0, category="hammer")
  drawn = study.draw_candidates(tool, 64, np.random.default_rng(0))
  for k, m in enumerate(tool.materials):  # within each part's material
    assert set(drawn[:, k]) <= set(material_slots(m).tolist())
  candidates = np.concatenate([drawn[:4], np.asarray(tool.slots)[None]])  # the truth last
  r = study.study_tool(tool, [300.0, 1000.0], candidates)
  assert r["best"] == list(tool.slots) and r["slots"] == list(tool.slots)
  for key in ("300", "1000"):  # the own shape's pick is the truth itself (distance 0)
    assert r[key]["own shape"] == list(tool.slots) and r[key]["motion_mm"] > 0
    assert r[key]["true boxes"] in candidates.tolist()
  assert r["300"]["motion_mm"] < r["1000"]["motion_mm"]
  s = study.summarize([r, r], [300.0, 1000.0])
  assert s["best"]["rmse"] == 0 and s["random_rmse"] > 0
  own = s["forces"]["1000"]["own shape"]
  assert own["rmse"] == 0 and own["explained"] == pytest.approx(1.0)
  assert own["within"] == {"0": 100.0, "2": 100.0, "4": 100.0}
  alone = study.study_tool(tool, [1000.0], candidates, readers=("own shape",))
  assert alone["1000"]["own shape"] == list(tool.slots) and "true boxes" not in alone["1000"]
  assert set(study.summarize([alone], [1000.0], ("own shape",))["forces"]["1000"]) == {
      "motion_mm_median", "diverged_candidates", "own shape"}


def test_tool_early_motion_reads_densities_from_velocities():
  """The study's regression recovers an exact linear law leaving each row out and not
  noise; `velocities` undoes `early_motion`'s compression; a hammer gives a row per part
  and configuration; the summary reads zero errors as zero."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from ppdjax.dataset import tools
  from tool_early_motion import run as study  # pylint: disable=import-outside-toplevel

  rng = np.random.default_rng(0)
  x = rng.normal(size=(30, 3))
  y = x @ np.array([[0.5, -1.0], [0.2, 0.0], [0.0, 2.0]]) + 1.0
  assert np.abs(study.loo_errors(x, y)).max() < 0.05  # ridge shrinks a little
  assert np.abs(study.loo_errors(rng.normal(size=(30, 3)), y)).mean() > 0.5
  t = np.arange(4)[:, None] * (1 / 300)
  traj = np.concatenate([t * np.array([0.4, 0.0, -0.1]), np.tile([1.0, 0, 0, 0], (4, 1))],
                        -1)[None].repeat(4, 0)  # (P, T, 7): sliding at 0.4 m/s, no spin
  lin, ang = study.velocities(traj, 2)
  np.testing.assert_allclose(lin.reshape(4, 2, 3), np.broadcast_to([0.4, 0, -0.1], (4, 2, 3)),
                             atol=1e-4)
  np.testing.assert_allclose(ang, 0.0, atol=1e-4)
  r = study.study_tool(tools.sample_tool(2026, 0, category="hammer"), 6, 1, rng)
  assert np.shape(r["linear velocity"]) == (6, 2) and np.shape(r["spread"]) == (6, 2)
  zero = {k: [[0.0, 0.0]] * 6 for k in study.READERS}
  summary = study.summarize([zero, zero])
  assert summary["linear velocity"]["median"] == 0.0 and summary["spread"]["mean"] == 0.0


def test_tool_density_ceiling_reads_box_parts_exactly_and_floors_hidden_ones():
  """A tool of two boxes (one turned about a tilted axis) has exactly its boxes' ten
  moments and gives their densities back from its mass properties alone; corrections skip
  empty readings and fall back to coarser keys; a bounded reading snaps into the
  material; the floor of one hidden metal box in four is its miss of metal's mean slot
  over two; the records' guesses are checked against the rebuilt slots."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  import trimesh  # pylint: disable=import-outside-toplevel
  from ppdjax import primitives  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import materials, tool_scene  # pylint: disable=import-outside-toplevel
  from tool_density_ceiling import run as study  # pylint: disable=import-outside-toplevel

  half = np.array([[0.3, 0.05, 0.04], [0.06, 0.1, 0.05]])
  pos = np.array([[-0.1, 0.0, -0.02], [0.26, 0.02, 0.07]])
  turn = trimesh.transformations.rotation_matrix(0.7, [0.3, 1.0, 0.5])
  parts = []
  for h, p, rot in zip(half, pos, (np.eye(4), turn)):
    box = trimesh.creation.box(extents=2 * h, transform=rot)
    box.apply_translation(p)
    parts.append(box)
  quat = np.stack([[1.0, 0, 0, 0], np.asarray(primitives.mat_to_quat(
      np.asarray(turn[:3, :3], np.float32)))])
  prims = primitives.Primitives(half_size=half.astype(np.float32),
                                pos=pos.astype(np.float32), quat=quat.astype(np.float32),
                                density=np.zeros(2, np.float32), valid=np.ones(2, bool))
  rho = np.array([700.0, 7800.0])
  target = study.tool_moments(*tool_scene.mass_properties(parts, rho))
  columns = study.box_moments(prims)
  np.testing.assert_allclose(columns @ rho, target, rtol=2e-4, atol=1e-3 * target[0])
  np.testing.assert_allclose(study.read_densities(columns, target), rho, rtol=1e-3)
  row = {"category": "knife", "count": 2, "slot": np.array([4, 80]),
         "raw": np.array([500.0, 40.0]), "material": ["wood", "metal"],
         "columns": columns, "target": target}
  table = study.corrections([row])  # the empty second box is not a correction
  assert table[("knife", 2, 0)] == pytest.approx(1.0) and ("knife", 2, 1) not in table
  np.testing.assert_allclose(study.box_corrections(row, table), [1.0, 1.0])
  np.testing.assert_allclose(study.read_in_material(row, np.ones(2)), rho, rtol=0.02)
  assert study.nearest_in_material("metal", 5000.0) == 3500.0  # metal's nearer range
  rows = [{"share": np.array([0.995, 0.005]), "material": ["wood", "metal"], "count": 2,
           "part": ["handle", "tip"], "category": "screwdriver", "tool": 0,
           "slot": np.array([4, 80])},
          {"share": np.array([0.5, 0.5]), "material": ["wood", "metal"], "count": 2,
           "part": ["handle", "tip"], "category": "screwdriver", "tool": 1,
           "slot": np.array([4, 81])}]
  out = study.floor(rows, 0.01)
  assert out["hidden_boxes_pct"] == 25.0 and out["hidden"] == {"screwdriver tip (metal)": 1}
  miss = 80 - materials.material_slots("metal").mean()
  assert out["rmse_floor"] == pytest.approx(abs(miss) / 2)
  rec = {("guess", "PPD"): np.array([[4, 70, -1], [5, 80, -1]]),
         ("true_slot",): np.array([[4, 80, 0], [4, 82, 0]]),
         ("true_valid",): np.array([[1, 1, 0], [1, 1, 0]], bool)}
  err, bad = study.network_errors(rec, rows)
  assert bad == [1] and list(err) == [0, -10, 1, -2]


def test_paired_models_reads_the_change_of_one_model_against_another():
  """Two hand-made record sets of the same 4 objects (2 geometries): the second has one
  more exact box and one more matched box; the change and F1 are those by hand; records
  of other objects are refused."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from paired_models import run as study  # pylint: disable=import-outside-toplevel

  def records(top1, matched):
    rec = {("true_slot",): np.array([1, 2, 3, 4]), ("mae", "PPD"): np.array([2.0, 2, 2, 2])}
    for k, v in {"top1": top1, "top5": [1, 1, 1, 1], "top10": [1, 1, 1, 1],
                 "sq_err": [0.0, 0, 0, 0], "count": [1, 1, 1, 1]}.items():
      rec[("counts", "PPD", k)] = np.asarray(v)
    rec.update({("shape", "matched"): np.asarray(matched), ("shape", "predicted"): np.ones(4),
                ("shape", "true"): np.ones(4)})
    return rec

  first, second = records([1, 0, 0, 0], [1, 1, 0, 0]), records([1, 1, 0, 0], [1, 1, 1, 0])
  out = study.compare(first, second, np.array([0, 0, 1, 1]), resamples=50)
  assert out["rows"]["PPD"]["top1"] == pytest.approx(25.0)
  assert out["rows"]["PPD"]["mae"] == 0.0 and list(out["rows"]) == ["PPD"]
  assert (out["shape_f1"]["first"], out["shape_f1"]["second"]) == (50.0, 75.0)
  other = records([1, 1, 0, 0], [1, 1, 1, 0])
  other[("true_slot",)] = np.array([4, 3, 2, 1])
  with pytest.raises(ValueError, match="not of the same"):
    study.compare(first, other, np.array([0, 0, 1, 1]))


@pytest.mark.slow  # three command lines, about 15 s on 2 cores
def test_tools_study_runs_some_variants_from_another_pretraining(tmp_path):
  """--variants keeps only those models' steps (no report without all three); --pretrained
  leaves out the towers and the pretraining, and must hold a finished one."""
  from ppdjax.training import checkpoints
  env = {**os.environ, "JAX_PLATFORMS": "cpu"}
  lister = lambda *a: subprocess.run(  # noqa: E731
      [sys.executable, "-m", "ppdjax.reproduce", "tools", "--list", "--config=ppdjax/configs/tools.py:tiny",
       f"--root={tmp_path / 'root'}", *a], cwd=ROOT, env=env, capture_output=True, text=True,
      timeout=300)
  pretrained = tmp_path / "other" / "pretrain"
  refused = lister("--variants=full", f"--pretrained={pretrained}")
  assert refused.returncode != 0 and "no finished pretraining" in refused.stderr
  os.makedirs(pretrained / checkpoints.LATEST / "1000000")  # a checkpoint past the end
  done = lister("--variants=full", f"--pretrained={pretrained}")
  assert done.returncode == 0, done.stderr[-2000:]
  assert [line.split()[1] for line in done.stdout.splitlines()] == [
      "generate:tools", "train:full", "evaluate:full", "floor"]
  bad = lister("--variants=full,no_voxels")
  assert bad.returncode != 0 and "--variants must be some of" in bad.stderr


def test_confusion_by_slot_reads_errors_by_true_slot_range():
  """Wood boxes (slot 5) all predicted exactly but one far off: exact and within-2 shares,
  mean error and RMSE by hand; heavy metal (slot 80) off by 8 and 10 slots."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from confusion_by_slot import run as confusion_by_slot  # pylint: disable=import-outside-toplevel
  m = np.zeros((100, 100), int)
  m[4, 4], m[4, 84] = 9, 1  # slot 5 (index 4): nine exact, one 80 slots off
  m[79, 87], m[79, 89] = 1, 1  # slot 80: 8 and 10 off
  wood, heavy = confusion_by_slot.by_range(m)
  assert (wood["range"], wood["boxes"], heavy["range"], heavy["boxes"]) == ("1-10", 10, "71-100", 2)
  assert wood["exact"] == 90.0 and wood["within_2"] == 90.0
  assert wood["mean_abs_slots"] == pytest.approx(8.0) and wood["rmse"] == pytest.approx(np.sqrt(640))
  assert heavy["exact"] == 0.0 and heavy["mean_abs_slots"] == pytest.approx(9.0)
  assert heavy["mean_abs_relative"] == pytest.approx(100 * 9 / 80)
  with pytest.raises(ValueError, match="square"):
    confusion_by_slot.by_range(np.zeros((100, 99)))


def test_tools_by_category_checks_the_records_order_against_rebuilt_tools():
  """A rebuilt tool's slots are those the dataset stores for its first configuration (as
  an evaluation records them); records that match pass the order check, and a tool whose
  records hold other slots (same box count) or another tool's fails it, so a wrong order
  is never read as categories."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from tools_by_category import run as tbc  # pylint: disable=import-outside-toplevel
  from ppdjax import primitives  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import storage, tool_generation  # pylint: disable=import-outside-toplevel
  from ppdjax.eval import baselines  # pylint: disable=import-outside-toplevel
  ids = tbc.test_tools(40, (0.8, 0.1, 0.1))
  assert len(ids) >= 2 and all(storage.split_of(ids) == 2)
  truths = [tbc.tool_truth(0, int(i)) for i in ids[:2]]
  assert all(c in tbc.tools.CATEGORIES for c, _ in truths)
  stored = tool_generation.tool_samples(0, int(ids[0]), image_size=16, steps=4)[0]
  as_evaluated = baselines.true_slots(primitives.Primitives(  # the records' true slots
      *[stored[f][None] for f in primitives.FIELDS]))[0]
  np.testing.assert_array_equal(as_evaluated, truths[0][1])
  slots = np.stack([s for _, s in truths])  # (tools, K)
  rec = {("true_slot",): np.repeat(slots, 2, axis=0),
         ("true_valid",): np.repeat(slots >= 0, 2, axis=0)}
  assert tbc.check_order(rec, truths, configs=2) == []
  other = {k: v.copy() for k, v in rec.items()}
  other[("true_slot",)][2, 0] += 1  # the second tool's own configuration, one slot off
  assert tbc.check_order(other, truths, configs=2) == [1]
  mixed = {k: v[[2, 3, 0, 1]] for k, v in rec.items()}
  assert tbc.check_order(mixed, truths, configs=2) == ([0, 1] if not np.array_equal(*slots)
                                                        else [])


def test_selection_horizon_study_reads_the_sweep_by_hand_and_chooses_on_the_first_split():
  """Four towers of two configurations (two boxes each). At 32 steps towers 0, 1 and 3 are
  exact and tower 2 is 3 slots off; at all steps tower 1 is off too. The rows, the choice
  and the paired change are those numbers; intervals draw whole towers (a tower's boxes hit
  or miss together, so every draw is a multiple of 25 %) and both rules together (the
  change is never negative); records without a horizon sweep, not whole towers, or in
  another order than the evaluation's intervals say, are refused."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from selection_horizon_study import run as shs  # pylint: disable=import-outside-toplevel
  n = 8
  rec = {("blocks",): np.full(n, 2)}
  for h, off_by_tower in ((32, [0, 0, 3, 0]), (0, [0, 3, 3, 0])):
    off = np.repeat(np.array(off_by_tower, float), 2)
    for k, v in (("top1", (off == 0).astype(int) * 2), ("top5", np.full(n, 2)),
                 ("top10", np.full(n, 2)), ("sq_err", (2 * off * off).astype(int)),
                 ("count", np.full(n, 2)), ("mae", off.astype(np.float32))):
      rec[("hsweep", "PPD+Fit+Sample", h, 0.0, k)] = v
  groups = shs.tower_groups({"geometries": 4}, n)
  np.testing.assert_array_equal(groups, [0, 0, 1, 1, 2, 2, 3, 3])
  rows = shs.horizon_rows(rec, groups, 0.0, resamples=200)["PPD+Fit+Sample"]
  assert list(rows) == ["32", "0"]  # all steps last
  assert rows["32"]["top1"] == 75.0 and rows["0"]["top1"] == 50.0
  assert rows["0"]["rmse"] == pytest.approx(np.sqrt(8 * 9 / 16))
  assert rows["0"]["table5"] == {"2": pytest.approx(np.sqrt(8 * 9 / 16))}
  for bound in rows["32"]["ci95"]["top1"] + rows["0"]["ci95"]["top1"]:
    assert bound % 25.0 == pytest.approx(0.0)  # whole towers drawn
  assert shs.choose(rows) == "32"
  change = shs.paired_change(rec, groups, "PPD+Fit+Sample", 0.0, 32, resamples=200)
  assert change["top1"] == 25.0 and change["rmse"] == pytest.approx(
      np.sqrt(4 * 9 / 16) - np.sqrt(8 * 9 / 16))
  assert change["ci95_top1"][0] >= 0.0 and change["ci95_top1"][1] > 0.0  # paired draws
  results = {"selection_horizon": 32, "table2": {"PPD+Fit+Sample": {"ci95": {
      "top1": rows["32"]["ci95"]["top1"], "rmse": rows["32"]["ci95"]["rmse"]}}}}
  shs.check_grouping({"PPD+Fit+Sample": rows}, results)
  results["table2"]["PPD+Fit+Sample"]["ci95"]["top1"] = [0.0, 100.0]
  with pytest.raises(ValueError, match="not in the evaluation's tower order"):
    shs.check_grouping({"PPD+Fit+Sample": rows}, results)
  with pytest.raises(ValueError, match="cannot be 3 towers"):
    shs.tower_groups({"geometries": 3}, n)
  with pytest.raises(ValueError, match="no horizon sweep"):
    shs.horizon_rows({("blocks",): np.full(n, 2)}, groups, 0.0)


def test_active_pushes_loop_picks_the_push_that_tells_hypotheses_apart():
  """Four candidates that move alike under every push but push 5, where they split in two
  pairs: after the paper's first push the active policy takes push 5, never repeats one,
  and each decomposition is the closest candidate over the pushes made."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from active_pushes import run as study  # pylint: disable=import-outside-toplevel

  s, n, t = 4, 8, 6
  sims = np.zeros((s, n, t, 7), np.float32)
  sims[..., 3] = 1.0  # identity quaternions
  sims[2:, 5, :, 0] = 0.1  # push 5 moves candidates 2 and 3 by 10 cm
  distances = np.full((s, n), 0.02, np.float32)
  distances[3] = 0.01  # candidate 3 is the closest under every push
  slots = np.asarray([[1, 2], [1, 3], [7, 2], [7, 3]], np.int32)
  out = jax.jit(lambda k: study.closed_loop(
      jnp.asarray(sims), jnp.asarray(distances), jnp.asarray(slots), jnp.ones(s, bool),
      jnp.zeros(s), jnp.ones(2, bool), k, paper=jnp.asarray([0, 1, 2, 3]), scale=1.0,
      power=1.0, hypotheses=4, given={"mine": jnp.asarray([7, 5, 6, 4])}))(jax.random.key(0))
  active = np.asarray(out["active"]["pushes"])
  assert active[0] == 0 and active[1] == 5 and len(set(active.tolist())) == 4
  assert np.asarray(out["fixed"]["pushes"]).tolist() == [0, 1, 2, 3]
  assert np.asarray(out["mine"]["pushes"]).tolist() == [7, 5, 6, 4]  # a policy's own order
  assert (np.asarray(out["mine"]["answer"]) == slots[3]).all()
  assert len(set(np.asarray(out["random"]["pushes"]).tolist())) == 4
  for policy in study.POLICIES:
    assert (np.asarray(out[policy]["answer"]) == slots[3]).all()
    lower, upper = np.asarray(out[policy]["lower"]), np.asarray(out[policy]["upper"])
    assert (lower <= slots[3]).all() and (slots[3] <= upper).all()


def test_expected_slot_error_picks_the_push_that_pins_the_free_box():
  """Two boxes; the push made pins box 0 only. Of two candidates, the one that tells box 1
  leaves the smaller expected error, and the error is the Laplace posterior's in closed
  form: ρ² / 100² · σ² / F (F ≫ σ² / prior²), the prior's variance for a box no push
  tells; a padded box counts nothing."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from active_pushes import design  # pylint: disable=import-outside-toplevel
  f = 1e4
  info = jnp.asarray([[[f, 0.0], [0.0, 0.0]],   # made: box 0
                      [[f, 0.0], [0.0, 0.0]],   # again box 0
                      [[0.0, 0.0], [0.0, f]]])  # box 1
  density, noise = jnp.asarray([1000.0, 3000.0]), 1e-4
  made = jnp.asarray([True, False, False])
  error = np.asarray(design.expected_slot_error(info, made, density, jnp.ones(2, bool),
                                                noise, prior_std=1.0))
  np.testing.assert_allclose(error[1], 100.0 * noise / (2 * f) + 900.0 * 1.0, rtol=1e-3)
  np.testing.assert_allclose(error[2], 100.0 * noise / f + 900.0 * noise / f, rtol=1e-3)
  assert error[2] < error[1]
  padded = design.expected_slot_error(info, made, density, jnp.asarray([True, False]), noise)
  np.testing.assert_allclose(np.asarray(padded)[1:], 100.0 * noise / np.asarray([2 * f, f]),
                             rtol=1e-3)


def test_push_information_is_the_squared_jacobian_and_cumulates_over_steps():
  """Through MuJoCo's C engine: a push too weak to move a tower tells nothing; a strong
  one tells about both boxes (positive diagonal), and its information over the first h
  steps matches JᵀJ of the differences taken by hand over those steps."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset.towers import sample_towers  # pylint: disable=import-outside-toplevel
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from active_pushes import design  # pylint: disable=import-outside-toplevel
  from ppdjax import metrics  # pylint: disable=import-outside-toplevel
  from ppdjax.infer import active  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.rollout_mjx import simulate  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.rollout_mujoco import MujocoSettings  # pylint: disable=import-outside-toplevel
  tower = jax.tree.map(lambda x: x[0], sample_towers(3, 1, num_blocks=2))
  pushes = active.candidate_pushes(azimuths=1, elevations=(0.0,), strengths=(1e-4, 2.0))
  settings = MujocoSettings()
  info, sim = jax.jit(lambda p: design.push_information(p, pushes, steps=32,
                                                        settings=settings))(tower)
  info = np.asarray(info)
  assert info.shape == (2, 32, 5, 5) and np.abs(info[0, -1]).max() < 1e-3 * info[1, -1, 0, 0]
  assert (np.diagonal(info[1, -1])[:2] > 0).all() and (np.diagonal(info[1, -1])[2:] == 0).all()
  step = 1e-3
  moved = tower.replace(density=tower.density * jnp.exp(step * jnp.eye(5)[0]))
  j0 = np.asarray(metrics.pose_residual(simulate(moved, pushes, steps=32, settings=settings),
                                        sim)) / step
  np.testing.assert_allclose(info[1, -1, 0, 0], np.sum(j0[1] ** 2), rtol=1e-2)  # rounding
  np.testing.assert_allclose(info[1, 15, 0, 0], np.sum(j0[1, :16] ** 2), rtol=1e-2)


def test_active_pushes_report_scores_the_refined_loop_and_checks_its_temperature(tmp_path):
  """The report scores each policy's refined answers (the candidates' intervals kept) beside
  the +Sample loop's at the prior weight validation chose (found by value: the records list
  their weights in other orders), picks the choosing policy of least refined RMSE on the
  validation records (the design loop there; the gain's loop would win on test) for
  "active", and refuses records refined at a temperature validation did not choose or
  holding other policies."""
  sys.path.insert(0, os.path.join(ROOT, "experiments"))
  from active_pushes import run as study  # pylint: disable=import-outside-toplevel

  towers, k, scales = 12, 3, np.asarray([0.3, 1.0])
  true = np.random.default_rng(0).integers(10, 60, (towers, k))

  def records(weights, offsets):  # offsets[policy]: the refined answer's error per weight
    rec = {"valid": np.ones((towers, k), bool), "true": true, "scales": scales,
           "prior_model": "m", "samples": 8, "hypotheses": 4, "power": 0.5,
           "setting": "depth", "refine_scale": 1.0, "all_answer": true + 1,
           "design_horizons": np.asarray([64]), "refine_weights": np.asarray(weights)}
    for p in study.POLICIES + ("design64",):
      answer = np.repeat((true + 2)[:, None, None], 2, 1).repeat(4, 2)  # (towers, S, M, K)
      width = np.asarray([1, 5])[None, :, None, None]  # validation picks scale 1.0: covers
      rec.update({f"{p}_answer": answer, f"{p}_lower": answer - width,
                  f"{p}_upper": answer + width,
                  f"{p}_pushes": np.tile(np.arange(4), (towers, 2, 1)),
                  f"{p}_refined_answer": np.stack([np.repeat((true + o)[:, None], 4, 1)
                                                   for o in offsets[p]], 1),  # (T, W, M, K)
                  f"{p}_refined_closer": np.ones((towers, len(weights), 4), bool)})
    return rec

  # validation: weight 1e-5 refines the fixed four exactly; the design loop beats the gain's
  val = records([0.0, 1e-5], {"fixed": (7, 0), "random": (7, 0), "active": (7, 1),
                              "design64": (7, 0)})
  # test, its weights in the other order: the gain's loop exact, the design loop 3 off
  test = records([1e-5, 0.0], {"fixed": (0, 7), "random": (0, 7), "active": (0, 7),
                               "design64": (3, 7)})
  np.savez(tmp_path / "val.npz", **val)
  np.savez(tmp_path / "test.npz", **test)
  out = tmp_path / "posterior.json"
  study.report(str(tmp_path / "val.npz"), str(tmp_path / "test.npz"), str(out))
  result = json.loads(out.read_text())
  by_setting = result["active_by_setting"]["depth"]
  refined = by_setting["refined"]
  assert refined["prior_weight"] == 1e-5  # validation's lowest RMSE
  assert refined["chosen_policy"] == "design64"  # on validation, not on test
  assert refined["validation_rmse4_by_policy"] == {"active": 1.0, "design64": 0.0}
  assert refined["active4"]["top1"] == 100.0 and refined["design644"]["rmse"] == 3.0
  assert refined["fixed4"]["rmse"] == 0.0
  assert refined["active4"]["coverage_90"] == 1.0  # the candidates' interval holds the truth
  assert refined["clipped"]["design644"]["rmse"] == 3.0  # inside the interval (5) already
  head = result["active"]
  assert head["policy"] == "design64" and head["loop"] == "refined"
  assert head["active4"]["rmse"] == 3.0 and head["setting"] == "depth"
  assert set(head["paired"]) == {"active2_minus_fixed4", "active2_minus_fixed2",
                                 "active4_minus_fixed4", "active4_minus_random4"}
  assert by_setting["active4"]["top1"] == 0.0  # +Sample's answers: two slots off
  assert by_setting["active4"]["rmse"] == pytest.approx(2.0)
  np.savez(tmp_path / "test.npz", **{**test, "refine_scale": 0.3})
  with pytest.raises(ValueError, match="--refine_scale=1.0"):
    study.report(str(tmp_path / "val.npz"), str(tmp_path / "test.npz"), str(out))
  np.savez(tmp_path / "val.npz", **{**val, "design_horizons": np.asarray([64, 256])})
  np.savez(tmp_path / "test.npz", **test)
  with pytest.raises(ValueError, match="record both alike"):
    study.report(str(tmp_path / "val.npz"), str(tmp_path / "test.npz"), str(out))
