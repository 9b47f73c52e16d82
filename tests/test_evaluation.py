"""Evaluation: the evaluate CLI, the evaluator's stages and records, resuming, errors
(apart from test_inference.py so that pytest's two workers share the load)."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppdjax
from ppdjax import metrics
from ppdjax.configs import tiny
from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import storage
from ppdjax.infer.config import DecomposeConfig, FitConfig, RefineConfig, SelectConfig
from ppdjax.eval import baselines, batches, evaluation, partial
from ppdjax.report import markdown, tables
from ppdjax.training import checkpoints
from conftest import cli_module

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PUSHES = ppdjax.default_pushes()
SAMPLES = tiny.get_config().eval.samples  # the demo's, so compilations are shared


def _evaluate_cli(tiny_run, tiny_dataset, tmp_path, *extra):
  """`python -m ppdjax.evaluate` run in this process (its main, after flag parsing; the
  error test below runs it as a separate process); returns (results, out dir)."""
  from absl import flags
  cli = cli_module("ppdjax.evaluate")
  out = str(tmp_path / "eval")
  argv = ["ppdjax.evaluate", f"--workdir={tiny_run[0]}", f"--data={tiny_dataset}",
          f"--out={out}", "--max_objects=8", *extra]
  flags.FLAGS.unparse_flags()
  # the --config.* overrides are registered from sys.argv when the config flag is parsed
  saved_argv, sys.argv = sys.argv, argv
  try:
    flags.FLAGS["config"].parse(flags.FLAGS["config"].default)
    flags.FLAGS(argv)
    cli.main([])
  finally:
    sys.argv = saved_argv
    flags.FLAGS.unparse_flags()
  with open(os.path.join(out, "results.json")) as f:
    results = json.load(f)
  return results, out


def test_evaluate_cli_writes_both_files(tiny_run, tiny_dataset, tmp_path):
  """Samples, batch size and τ come from the run's preset; refinement's start is recorded
  only where there is a refinement."""
  results, out = _evaluate_cli(tiny_run, tiny_dataset, tmp_path, "--config.eval.studies=True")
  assert results["refine"] is False and results["headline"] == "PPD+Sample"
  assert results["decompose"] == DecomposeConfig.from_eval(tiny.get_config().eval).to_dict()
  rows = results["table2"]
  assert set(rows) == {"Frequent", "Nearest", "Oracle", "PPD", "PPD+Sample"}
  lo, hi = rows["PPD"]["ci95"]["rmse"]
  assert lo <= rows["PPD"]["rmse"] <= hi
  for row in rows.values():
    assert 0 <= row["top1"] <= row["top5"] <= row["top10"] <= 100 and row["mae"] >= 0
  assert rows["Oracle"]["top10"] > rows["Frequent"]["top10"]
  # Frequent's one slot: the training split's commonest box label
  train = storage.open_dataset(tiny_dataset, "train")
  labels = baselines.true_slots(train.take(np.arange(len(train)), keys=("primitives",))["primitives"])
  assert results["frequent_slot"] == np.bincount(labels[labels >= 0]).argmax()
  assert set(results["table4"]) == {"PPD", "Sample Phys.", "Sample Phys.+Shape"}
  for r in results["table4"].values():  # MAE (mm) of the best of 1, 8, S by distance
    assert set(r) == {"1", "8", str(SAMPLES)} and all(0 < v < 2000 for v in r.values())
  assert results["table4"]["PPD"]["1"] == pytest.approx(rows["PPD"]["mae"])
  assert results["objects"] == 8 and results["samples"] == SAMPLES
  # by material of the true box, and per object: both add up to the rows' scores
  for name in ("PPD", "PPD+Sample"):
    per = {m: v for m, v in results["by_material"][name].items() if m != "range_confusions"}
    boxes = sum(v["boxes"] for v in per.values())
    top1 = sum(v["boxes"] * v["top1"] for v in per.values()) / boxes
    assert top1 == pytest.approx(rows[name]["top1"])
    assert 0 <= results["by_material"][name]["range_confusions"] <= 100
    hits = results["per_object"][name]
    assert len(hits["count"]) == 8 and sum(hits["count"]) == boxes
    assert 100 * sum(hits["top1"]) / boxes == pytest.approx(rows[name]["top1"])
  # the intervals resample whole towers (their configurations share a shape)
  test = storage.open_dataset(tiny_dataset, "test")
  towers = np.unique(test.take(np.arange(len(test)), keys=("tower_id",))["tower_id"])
  assert results["intervals_over"] == "geometries" and results["geometries"] == len(towers)
  assert results["prior_weight"] == tiny.get_config().eval.prior_weight
  text = open(os.path.join(out, "results.md")).read()
  assert "Table 2" in text and "Table 4" in text and "| PPD+Sample |" in text
  assert results["data_kind"] == "towers"
  assert f"intervals over the {len(towers)} towers (each" in text
  assert os.path.exists(os.path.join(out, "confusion.png"))
  # the oracle's pick among the same samples: at most +Sample's RMSE, top-1 within coverage
  o = results["oracle_pick"]["PPD+Sample"]
  assert o["rmse"] <= rows["PPD+Sample"]["rmse"] + 1e-9 and o["top1"] <= o["coverage"] + 1e-9
  assert "+Sample's ceiling" in text
  # where the time went: the first batch (compilation), then each jitted stage per batch
  stages = results["seconds_by_stage"]
  assert stages["batches_after_first"] >= 0 and stages["first_batch"] >= stages["compile"] >= 0
  assert set(stages["after_first"]) >= {"decode", "sample", "host"}
  assert "compile" not in stages["after_first"]  # on a CPU the stages compile when called
  assert "first batch" in text


@pytest.mark.slow  # the fits compile inside the evaluation: about a minute more on 2 cores
def test_evaluate_cli_with_the_fit_rows(tiny_run, tiny_dataset, tmp_path):
  results, _ = _evaluate_cli(tiny_run, tiny_dataset, tmp_path, "--config.eval.fit=True",
                             "--config.eval.depth=True", "--config.eval.true_shapes=True",
                             "--config.eval.image_fit=True")
  rows = results["table2"]
  assert set(rows) == {"Frequent", "Nearest", "Oracle", "PPD", "PPD+Sample",
                       "PPD+Fit(depth)", "PPD+Fit(depth)+Sample",
                       "PPD+True boxes", "PPD+True boxes+Sample"}
  assert results["headline"] == "PPD+Fit(depth)+Sample"
  # the fit reads the tiny towers' boxes exactly; densities are the network's either way
  assert results["shape_fit_depth"]["f1"] == 100.0
  assert results["shape_fit_depth"]["count_exact"] == 100.0
  for name in ("PPD+Fit(depth)", "PPD+True boxes"):
    assert {k: rows[name][k] for k in ("top1", "rmse")} == {
        k: rows["PPD"][k] for k in ("top1", "rmse")}
  lo, hi = rows["PPD"]["ci95"]["rmse"]
  assert lo <= rows["PPD"]["rmse"] <= hi
  assert set(results["table4"]) == {"PPD", "PPD+Fit(depth)", "PPD+True boxes",
                                    "Sample Phys.", "Sample Phys.+Shape"}
  assert results["table4"]["PPD+Fit(depth)"]["1"] == pytest.approx(rows["PPD+Fit(depth)"]["mae"])
  assert results["depth"] and results["fit"] and results["true_shapes"] and results["image_fit"]
  faces = results["face_error_mm"]  # the voxel fit's faces lie within half a voxel (15.6 mm)
  assert set(faces) == {"ppd", "fit_depth"}
  # and the image and the depth move them by half a voxel at most
  assert faces["fit_depth"]["max"] <= 31.3


def test_the_oracle_pick_takes_the_sample_closest_to_the_truth():
  """Hand case: two boxes (a third not in the tower), three samples; the second is one
  slot off on each box, the others far on one; box 0's true slot is in no sample."""
  from ppdjax.eval import rows
  slots = np.array([[[40, 11, 0], [21, 12, 0], [90, 10, 0]]])  # (B=1, S=3, K=3)
  slot, valid = np.array([[20, 11, -1]]), np.array([[True, True, False]])
  logits = np.zeros((1, 3, 100))
  rec = rows.oracle_pick("PPD+Sample", logits, slots, slot, valid, np.array([[1, 1, 0]], bool))
  # picked: sample 1 (errors 1 + 1 = 2; sample 0: 400 + 0; sample 2: 4900 + 1)
  assert rec[("oracle_pick", "PPD+Sample", "sq_err")].sum() == pytest.approx(2.0)
  assert rec[("oracle_pick", "PPD+Sample", "top1")].sum() == 0  # one off on both boxes
  np.testing.assert_array_equal(rec[("coverage", "PPD+Sample")], [[False, True, False]])


def test_the_posterior_marginal_sums_the_candidates_of_each_slot():
  """Hand case: three candidates for two boxes. Candidate 0 is closest, but candidates 1
  and 2 (nearly as close, and together more probable) agree on box 0's slot, so the
  marginal reads their slot on box 0 and candidate 0's on box 1 (its weight is the larger
  of the two that hold slot 12 there); far below T the marginal is the closest pick."""
  from ppdjax.eval import rows
  slots = np.array([[[30, 12], [31, 12], [31, 13]]])  # (B=1, S=3, K=2)
  dist = np.array([[1.0e-3, 1.1e-3, 1.2e-3]])
  logp = np.log(np.array([[0.2, 0.3, 0.3]]))
  valid, slot = np.ones((1, 2), bool), np.array([[31, 12]])
  logits = np.zeros((1, 2, 100))
  w = rows.posterior_weights(dist, logp, 1e-3)
  assert w.max() == 0.0 and np.argmax(w) == 1  # best: 0.3·e^-0.1 > 0.2
  scores = rows.posterior_scores(logits, slots, w, valid)
  np.testing.assert_array_equal(np.argmax(scores, -1), [[31, 12]])
  mass = np.exp(w[0])
  assert scores[0, 0, 31] - scores[0, 0, 30] == pytest.approx(
      np.log((mass[1] + mass[2]) / mass[0]))
  assert np.all(scores[0, 0, 32:] < scores[0, 0, 30])  # unsampled slots rank below
  sharp = rows.posterior_scores(logits, slots, rows.posterior_weights(dist, logp, 1e-6), valid)
  np.testing.assert_array_equal(np.argmax(sharp, -1), [[30, 12]])
  relative = rows.posterior_weights(dist, logp, "rel:1")  # T = the least distance
  np.testing.assert_allclose(relative, w)
  rec = rows.posterior_records("PPD+Sample", logits, slots, dist, logp,
                               np.array([[5.0, 6.0, 7.0]]), valid, slot, valid)
  assert rec[("posterior", "PPD+Sample", 1e-3, "top1")].sum() == 2
  assert rec[("posterior", "PPD+Sample", 1e-3, "mae")][0] == 6.0  # the heaviest candidate
  assert rec[("posterior", "PPD+Sample", 1e-4, "sq_err")].sum() == 1  # closest: 30 on box 0


def test_sample_rows_pick_the_closest_candidate_at_micrometre_distances():
  """+Sample's rows read the candidate that `argmin` of the objective picks, however close
  the distances: at τ = 0 they are metres of a few micrometres' difference (a float32
  offset once tied them all and the lowest slot won)."""
  from ppdjax.eval import rows
  out, slot, base, layout = _fake_batch_output(b=8, s=64)
  out["hdist"] = 2e-3 + 1e-6 * out["hdist"]  # 2 mm apart by at most a micrometre
  out["dist"] = out["hdist"][..., tables.SELECTION_HORIZONS.index(0)]
  rec = rows.batch_records(out, slot, slot >= 0, base, samples=64, prior_weight=0.0,
                           prefixes=(1, 64), with_baselines=True, refine=False, layout=layout,
                           headline="fit", screen=(32, 64))
  for name, group, slots in (("PPD+Sample", "ppd", out["slots"]),
                             ("PPD+Fit+Sample", "fit", out["fit_slots"]["fit"])):
    picked = slots[np.arange(8), np.argmin(out["dist"][:, layout[group]], -1)]
    np.testing.assert_array_equal(rec[("guess", name)], picked, name)
    valid = slot >= 0
    np.testing.assert_array_equal(rec[("counts", name, "top1")],
                                  ((picked == slot) & valid).sum(-1), name)
    np.testing.assert_array_equal(rec[("counts", name, "sq_err")],
                                  np.where(valid, (picked - slot) ** 2, 0).sum(-1), name)


def test_the_network_boxes_row_selects_with_its_own_tau():
  """PPD+Sample (the network's boxes) reads `network_prior_weight`, the fitted row
  `prior_weight`: each picks argmin of distance - tau log prior with its own tau."""
  from ppdjax.eval import rows
  from ppdjax.infer import sampling
  out, slot, base, layout = _fake_batch_output(b=8, s=64)
  kw = dict(samples=64, prefixes=(1, 64), with_baselines=True, refine=False, layout=layout,
            headline="fit")
  rec = rows.batch_records(out, slot, slot >= 0, base, prior_weight=0.0,
                           network_prior_weight=10.0, **kw)
  same = rows.batch_records(out, slot, slot >= 0, base, prior_weight=0.0, **kw)
  h = tables.SELECTION_HORIZONS.index(0)
  for tau, r in ((10.0, rec), (0.0, same)):
    objective = sampling.selection_objective(out["hdist"][:, layout["ppd"], h], out["logp"], tau)
    picked = out["slots"][np.arange(8), np.argmin(objective, -1)]
    np.testing.assert_array_equal(r[("guess", "PPD+Sample")], picked)
  np.testing.assert_array_equal(rec[("guess", "PPD+Fit+Sample")],
                                same[("guess", "PPD+Fit+Sample")])
  assert (rec[("guess", "PPD+Sample")] != same[("guess", "PPD+Sample")]).any()


def _fake_batch_output(b=4, s=16, k=3, seed=0):
  """What `Evaluator.batch` returns for b objects, with random candidates: the network's
  boxes, one voxel-fit group and the baselines."""
  from types import SimpleNamespace
  from ppdjax.eval.groups import candidate_layout
  rng = np.random.default_rng(seed)
  layout = candidate_layout(s, ("fit",), True)
  c = max(x.stop for x in layout.values())
  boxes = SimpleNamespace(valid=np.ones((b, k), bool))
  shape = {n: np.ones(b) for n in ("matched", "predicted", "true")}
  out = {"pred": boxes, "logits": rng.normal(size=(b, k, 100)), "shape": shape,
         "slots": rng.integers(0, 100, (b, s, k)), "logp": rng.normal(size=(b, s)),
         "hdist": rng.random((b, c, len(tables.SELECTION_HORIZONS))), "mae": rng.random((b, c)),
         "faces": {"ppd": rng.random((b, k, 6))}, "fitted": {"fit": boxes},
         "group_logits": {"fit": rng.normal(size=(b, k, 100))}, "shape_fit": shape,
         "fit_slots": {"fit": rng.integers(0, 100, (b, s, k))},
         "fit_logp": {"fit": rng.normal(size=(b, s))}}
  out["dist"] = out["hdist"][..., tables.SELECTION_HORIZONS.index(0)]
  slot = rng.integers(0, 100, (b, k))
  return out, slot, rng.normal(size=(b, 3, k, 100)), layout


def test_the_selection_horizon_picks_by_the_distance_over_its_steps():
  from ppdjax.eval import rows
  out, slot, base, layout = _fake_batch_output()
  kw = dict(samples=16, prior_weight=0.0, prefixes=(1, 8, 16), with_baselines=True,
            refine=False, layout=layout)
  full = rows.batch_records(out, slot, slot >= 0, base, **kw)
  swept = rows.batch_records(out, slot, slot >= 0, base, selection_horizon=32,
                             horizon_sweep=True, studies=True, **kw)
  h32 = tables.SELECTION_HORIZONS.index(32)
  # τ = 0 at 32 steps: the +Sample row's MAE is that of the candidate closest over 32 steps
  d = out["hdist"][:, layout["ppd"], h32]
  expect = out["mae"][:, layout["ppd"]][np.arange(4), d.argmin(-1)]
  np.testing.assert_allclose(swept[("mae", "PPD+Sample")], expect)
  np.testing.assert_allclose(swept[("hsweep", "PPD+Sample", 0, 0.0, "mae")],
                             full[("mae", "PPD+Sample")])
  assert not any(k[0] == "hsweep" for k in full)  # only when asked
  # Table 4's best of N stays on the whole trajectory whatever the selection horizon
  np.testing.assert_array_equal(swept[("prefix", "PPD", 8)], full[("prefix", "PPD", 8)])
  with pytest.raises(ValueError, match="selection_horizon"):
    rows.batch_records(out, slot, slot >= 0, base, selection_horizon=33, **kw)


def test_refinement_starts_from_the_closest_candidate_among_the_screens_survivors():
  """`Evaluator._best_sample`: the start is the candidate closest over the whole trajectory,
  for `decompose`'s group among those its screen keeps (as `decompose` refines); the
  distance handed on is the start's."""
  from types import SimpleNamespace
  from ppdjax.eval.evaluator import Evaluator, slot_to_density
  out, _, _, layout = _fake_batch_output(b=4, s=16)
  fit = out["hdist"][:, layout["fit"]]  # a view: edits reach out["hdist"]
  h32, h0 = tables.SELECTION_HORIZONS.index(32), tables.SELECTION_HORIZONS.index(0)
  fit[:, 3, h0] = -1.0   # candidate 3 is the closest over all steps,
  fit[:, 3, h32] = 9.0   # but the farthest over the first 32: a screen drops it
  fit[:, 7, h0] = -0.5   # candidate 7 is the next closest and survives
  fit[:, 7, h32] = -1.0
  out["dist"] = out["hdist"][..., h0]
  boxes = SimpleNamespace(replace=lambda density: density)  # the start's densities
  decoded = {"fitted": {"fit": boxes}, "group_logits": {"fit": out["group_logits"]["fit"]}}
  starts = {}
  for steps in (0, 32):
    select = SelectConfig(samples=16, screen_steps=steps, screen_keep=8)
    ev = SimpleNamespace(layout=layout, refine_group="fit",
                         decompose=DecomposeConfig(select=select))
    starts[steps] = Evaluator._best_sample(ev, out, decoded, "fit")
  for steps, pick in ((0, 3), (32, 7)):
    density, _, d0, m0 = starts[steps]
    expect = slot_to_density(out["fit_slots"]["fit"][:, pick])
    np.testing.assert_allclose(np.asarray(density), np.asarray(expect, np.float32))
    np.testing.assert_array_equal(d0, out["dist"][:, layout["fit"]][:, pick])
    np.testing.assert_array_equal(m0, out["mae"][:, layout["fit"]][:, pick])


def test_the_screen_replay_keeps_the_winner_only_when_it_survives_the_prefix():
  """`rows.screen_records`: the pick is the best by the row's objective among the `keep`
  closest over the first `steps` steps; 'same' says whether that is the exhaustive pick."""
  from ppdjax.eval import rows
  out, slot, base, layout = _fake_batch_output(b=8, s=64)
  h16, h0 = tables.SELECTION_HORIZONS.index(16), tables.SELECTION_HORIZONS.index(0)
  ppd = out["hdist"][:, layout["ppd"]]  # a view: edits reach out["hdist"]
  ppd[:4, 5, h16] = -1.0   # objects 0-3: candidate 5 wins over all steps and survives
  ppd[:, 5, h0] = -1.0
  ppd[4:, 5, h16] = 9.0    # objects 4-7: it is the farthest over the first 16 steps
  out["dist"] = out["hdist"][..., h0]
  rec = rows.batch_records(out, slot, slot >= 0, base, samples=64, prior_weight=0.0,
                           prefixes=(1,), with_baselines=True, refine=False, layout=layout,
                           studies=True)
  same = rec[("screen", "PPD+Sample", 16, 32, "same")]
  np.testing.assert_array_equal(same, [True] * 4 + [False] * 4)
  np.testing.assert_array_equal(rec[("screen", "PPD+Sample", 16, 32, "mae")][:4],
                                out["mae"][:4, layout["ppd"]][:, 5])
  assert ("screen", "PPD+Fit+Sample", 32, 32, "top1") in rec
  assert ("screen", "PPD+Sample", 64, 64, "same") not in rec  # keeps every candidate
  results = tables.summarize({}, rec)
  assert results["screens"]["PPD+Sample"]["16:32"]["same_pick"] == pytest.approx(50.0)
  assert any(line.startswith("| PPD+Sample | 16 → 32 | 50.0") for line in markdown.screen_md(results))


def test_the_records_count_hits_as_the_metrics_do():
  from ppdjax.eval import rows
  rng = np.random.default_rng(3)
  scores = rng.integers(0, 5, (6, 4, 100)).astype(np.float32)  # many ties
  slot, valid = rng.integers(-1, 100, (6, 4)), rng.random((6, 4)) > 0.3
  want = metrics.density_counts(jnp.asarray(scores), jnp.asarray(np.maximum(slot, 0)),
                                jnp.asarray(valid))
  got = rows.row_counts(scores, slot, valid)
  for k, v in want.items():
    np.testing.assert_array_equal(got[k], np.asarray(v), err_msg=k)


def test_batches_are_read_ahead_in_order_once_each():
  import threading
  seen, started = [], {}
  second_read_early = threading.Event()

  def read(start):
    started[start] = threading.current_thread().name
    seen.append(start)
    if start == 20:
      second_read_early.set()
    return start * 2

  out = []
  for start, item in batches.read_ahead(read, range(0, 30, 10), prefetch=True):
    if start == 10:  # batch 20 is read while batch 10 is being worked on
      assert second_read_early.wait(5)
    out.append((start, item))
  assert out == [(0, 0), (10, 20), (20, 40)] and sorted(seen) == [0, 10, 20]
  assert all(name != threading.current_thread().name for name in started.values())
  plain = list(batches.read_ahead(read, range(0, 30, 10), prefetch=False))
  assert plain == out and read.waited >= 0


def test_evaluation_subsets():
  np.testing.assert_array_equal(batches.evaluation_objects(10), np.arange(10))
  np.testing.assert_array_equal(batches.evaluation_objects(10, 3), [0, 1, 2])
  np.testing.assert_array_equal(batches.evaluation_objects(10, 3, "spread"), [0, 4, 9])
  assert len(batches.evaluation_objects(4800, 128, "spread")) == 128
  np.testing.assert_array_equal(batches.evaluation_objects(5, 9, "spread"), np.arange(5))
  with pytest.raises(ValueError, match="subset"):
    batches.evaluation_objects(10, 3, "random")


def test_evaluate_errors_name_the_problem(tiny_run, tiny_dataset, tmp_path):
  with pytest.raises(checkpoints.CheckpointError, match="config.json"):
    evaluation.evaluate(str(tmp_path), tiny_dataset)
  empty = tmp_path / "empty"
  empty.mkdir()
  with pytest.raises(storage.DatasetError, match="no dataset|manifest"):
    evaluation.evaluate(tiny_run[0], str(empty))
  from ppdjax.configs.schema import ConfigError
  with pytest.raises(ValueError, match="face_spread must be in"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, fit=True, face_spread=-0.1)
  with pytest.raises(ValueError, match="need fit.enabled"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, face_spread=0.5)
  with pytest.raises(ValueError, match="need fit.enabled"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, image_fit=True)
  with pytest.raises(ConfigError, match="refine_horizon"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, refine=True, refine_horizon=32)
  with pytest.raises(ConfigError, match="config.eval has no key sample"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, sample=3)
  with pytest.raises(ValueError, match="selection_horizon must be one of"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, selection_horizon=33)
  from ppdjax.eval.evaluator import Evaluator
  with pytest.raises(ValueError, match="with face_spread, no refinement"):
    Evaluator(*checkpoints.load(tiny_run[0]), DecomposeConfig(
        select=SelectConfig(samples=2), fit=FitConfig(face_spread=0.5),
        refine=RefineConfig(enabled=True)))
  with pytest.raises(ConfigError, match="refine.starts > 1 refines several"):
    Evaluator(*checkpoints.load(tiny_run[0]), DecomposeConfig(
        select=SelectConfig(samples=4), refine=RefineConfig(enabled=True, starts=2)))
  done = subprocess.run([sys.executable, "-m", "ppdjax.evaluate", f"--workdir={tmp_path}",
                         f"--data={tiny_dataset}"], cwd=ROOT, capture_output=True, text=True,
                        env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=300)
  assert done.returncode != 0 and "not a training workdir" in done.stderr
  # the same exit, in this process (a second interpreter costs seconds of imports)
  with pytest.raises(SystemExit, match="reads only config.eval"):
    _evaluate_cli(tiny_run, tiny_dataset, tmp_path, "--config.model.feature=3")


@pytest.mark.slow  # two evaluations (~26 s on 2 cores): `make test-all`; the records' round
# trip and resumption are pinned by the unit tests at the end of this module
def test_saved_batch_records_give_back_the_same_tables(tiny_run, tiny_dataset, tmp_path):
  """A rerun over saved batches computes (and compiles) nothing and reports the same; a
  folder of another evaluation is refused, naming what differs."""
  e = tiny.get_config().eval  # the evaluate command's settings: its programs are on disk,
  kw = dict(samples=e.samples, batch_size=e.batch_size, max_objects=8,  # bar the candidates'
            # simulation, which calls MuJoCo C from the host and so is compiled again
            prior_weight=e.prior_weight, progress=False, partial_dir=str(tmp_path / "partial"))
  first = evaluation.evaluate(tiny_run[0], tiny_dataset, prefetch=False, **kw)
  again = evaluation.evaluate(tiny_run[0], tiny_dataset, max_seconds=1e-9, **kw)
  for name, row in first["table2"].items():
    for k in ("top1", "top5", "rmse", "mae"):
      assert again["table2"][name][k] == row[k], (name, k)
  with pytest.raises(partial.OtherEvaluation, match="samples"):
    evaluation.evaluate(tiny_run[0], tiny_dataset, **{**kw, "samples": e.samples + 1})


def test_table4_batches_are_spread_and_cover_what_was_asked():
  np.testing.assert_array_equal(batches.table4_batches([64] * 75, 0), np.arange(75))
  chosen = batches.table4_batches([64] * 75, 1000)
  assert len(chosen) == 16 and chosen[0] == 0 and chosen[-1] == 74
  assert np.all(np.diff(chosen) >= 4)  # spread over the split, not its first batches
  sizes = [8, 8, 8, 1]  # a short last batch does not count as a whole one
  assert np.asarray(sizes)[batches.table4_batches(sizes, 10)].sum() >= 10
  np.testing.assert_array_equal(batches.table4_batches(sizes, 99), np.arange(4))
  with pytest.raises(ValueError, match="table4_objects"):
    batches.table4_batches(sizes, -1)


def _records_of(ev, out, samples, table4):
  """`rows.batch_records` of an `Evaluator.batch` output (every answer slot 0, no baselines'
  scores): what the evaluation would record of that batch."""
  b, k = out["logits"].shape[:2]
  slot = np.zeros((b, k), np.int32)
  return ev.records(out, slot, slot >= 0, np.zeros((b, 3, k, 100)), prefixes=(1, 8),
                    table4=table4)


def _tiny_evaluator(config, tiny_dataset):
  """(model -> an Evaluator of the tiny preset's evaluation with Table 4 on every batch,
  the evaluate command's first test batch: the CLI test's, whose programs are on disk)."""
  from ppdjax.eval.evaluator import Evaluator
  from ppdjax.sim.rollout_mjx import settings_for
  e = tiny.get_config().eval
  test = storage.open_dataset(tiny_dataset, "test")
  batch = test.take(np.arange(e.batch_size), keys=OBS_KEYS + ("primitives",))
  return (lambda model: Evaluator(model, config, DecomposeConfig.from_eval(e),
                                  pushes=test.pushes, settings=settings_for(test.engine),
                                  table4_every_batch=True)), batch


@pytest.mark.slow  # a check of what compiles: about a minute on 2 cores; `make test-all`
def test_stages_compile_once_side_by_side(tiny_run, tiny_dataset):
  """`Evaluator.compile` compiles every stage before the first batch, each in its own
  thread, on stand-ins shaped and placed as the batches' inputs: the batches then add no
  compiled signature. With Table 4 on every batch its candidates are simulated in the
  sampling call, and a batch cannot skip them."""
  model, config = checkpoints.load(tiny_run[0])
  make, batch = _tiny_evaluator(config, tiny_dataset)
  ev = make(model)
  ev.compile(batch, jax.random.key(0))
  stages = {"decode": ev._decode, "sample": ev._simulate}
  assert {k: f._cache_size() for k, f in stages.items()} == dict.fromkeys(stages, 1)
  assert ev._simulate_table4._cache_size() == 0  # not needed: one program fewer to compile
  out = ev.batch(batch, None, jax.random.key(1))
  assert out["mae"].shape[1] == ev.layout["shapes"].stop
  rec = _records_of(ev, out, ev.samples, table4=True)
  assert ("prefix", "Sample Phys.", 8) in rec and ("prefix", "PPD", 8) in rec
  assert {k: f._cache_size() for k, f in stages.items()} == dict.fromkeys(stages, 1)
  with pytest.raises(ValueError, match="table4_every_batch"):
    ev.batch(batch, None, jax.random.key(2), table4=False)


@pytest.mark.slow  # compiles the stages twice into an empty cache: about two minutes
def test_stages_compiled_ahead_are_loaded_from_the_persistent_cache(tiny_run, tiny_dataset,
                                                                    tmp_path):
  """`Evaluator.compile(execute=False)`, from a model with other weights, runs nothing and
  puts the stages' programs in the persistent cache, where another Evaluator's `compile`
  loads them (what `ppdjax.reproduce blocks`'s compile:full step relies on)."""
  from flax import nnx
  from jax._src import compilation_cache
  from ppdjax.nn.model import PPD
  model, config = checkpoints.load(tiny_run[0])
  make, batch = _tiny_evaluator(config, tiny_dataset)
  suite_cache = jax.config.jax_compilation_cache_dir
  jax.config.update("jax_compilation_cache_dir", str(tmp_path))  # empty
  compilation_cache.reset_cache()
  try:
    ahead = make(PPD(config.model, rngs=nnx.Rngs(7)))
    ahead.compile(batch, jax.random.key(0), execute=False)
    assert not ahead.compiled and ahead._simulate._cache_size() == 0
    hits = []
    jax.monitoring.register_event_listener(
        lambda name, **kw: hits.append(name) if name.endswith("/cache_hits") else None)
    ev = make(model)
    ev.compile(batch, jax.random.key(0))
    assert len(hits) >= 2  # decode and sample at least: loaded, not compiled
    assert ev.compiled and ev._simulate._cache_size() == 1
  finally:
    jax.config.update("jax_compilation_cache_dir", suite_cache)
    compilation_cache.reset_cache()


@pytest.mark.slow  # three more compiled programs on a CPU: about two minutes
def test_table4_is_reported_on_its_batches_only(tiny_run, tiny_dataset):
  """With `table4_objects`, Table 4's sampling baselines run on whole batches covering at
  least that many objects, and Table 4 is reported on those; Table 2 on every object.
  Simulated in a call of their own, they score what the sampling call scores with them."""
  from ppdjax.eval.evaluator import Evaluator
  from ppdjax.sim.rollout_mjx import settings_for
  e = tiny.get_config().eval
  r = evaluation.evaluate(tiny_run[0], tiny_dataset, samples=e.samples, batch_size=4,
                          max_objects=8, table4_objects=3, progress=False)
  assert r["objects"] == 8 and r["table4_evaluated"] == 4  # one whole batch of 4
  assert set(r["table4"]) >= {"PPD", "Sample Phys.", "Sample Phys.+Shape"}
  assert r["table2"]["Oracle"]["mae"] is not None  # Table 2's baselines on every batch
  model, config = checkpoints.load(tiny_run[0])
  test = storage.open_dataset(tiny_dataset, "test")
  batch = test.take(np.arange(4), keys=OBS_KEYS + ("primitives",))
  kw = dict(pushes=test.pushes, settings=settings_for(test.engine))
  apart = Evaluator(model, config, DecomposeConfig.from_eval(e), **kw)
  fused = Evaluator(model, config, DecomposeConfig.from_eval(e), **kw, table4_every_batch=True)
  both = [ev.batch(batch, None, jax.random.key(0)) for ev in (apart, fused)]
  for key in ("mae", "hdist"):  # the same rollouts, batched differently
    np.testing.assert_allclose(both[0][key], both[1][key], rtol=1e-4, atol=1e-5)
  out = apart.batch(batch, None, jax.random.key(1), table4=False)
  assert out["mae"].shape[1] == apart.layout["baselines"].stop
  rec = _records_of(apart, out, e.samples, table4=False)
  assert ("prefix", "Sample Phys.", 8) not in rec and ("prefix", "PPD", 8) not in rec
  assert apart._simulate_table4._cache_size() == 1


@pytest.mark.slow  # three evaluations: about 40 s on 2 cores
def test_a_paused_evaluation_resumes_to_the_same_results(tiny_run, tiny_dataset, tmp_path):
  """Records are saved per batch; a call stopped by its time budget goes on where it
  stopped, and the tables equal those of one uninterrupted call."""
  kw = dict(samples=SAMPLES, batch_size=4, max_objects=8, baselines=False,
            progress=False)
  folder = str(tmp_path / "partial")
  with pytest.raises(partial.EvaluationPaused, match="4 of 8 objects") as paused:
    evaluation.evaluate(tiny_run[0], tiny_dataset, partial_dir=folder, max_seconds=1e-9, **kw)
  assert paused.value.done == 4
  assert sorted(os.listdir(folder)) == ["batch-0000000.npz", "settings.json"]
  resumed = evaluation.evaluate(tiny_run[0], tiny_dataset, partial_dir=folder, **kw)
  straight = evaluation.evaluate(tiny_run[0], tiny_dataset, **kw)
  assert resumed["objects"] == straight["objects"] == 8
  for name, row in straight["table2"].items():
    for k in ("top1", "top5", "rmse", "mae"):
      assert resumed["table2"][name][k] == pytest.approx(row[k]), (name, k)


_TWO_DEVICES = """
import json, sys
import jax
from ppdjax.eval import evaluation
assert jax.local_device_count() == 2, jax.devices()
workdir, data, out, kw = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
r = evaluation.evaluate(workdir, data, **kw)
json.dump({"table2": r["table2"], "f1": r["f1"], "batch_size": r["batch_size"]}, open(out, "w"))
"""


@pytest.mark.slow  # a second process compiles the evaluation for two devices: ~2 min
def test_an_evaluation_split_over_two_devices_gives_the_same_tables(tiny_run, tiny_dataset,
                                                                   tmp_path):
  """Each local device takes its share of every batch (`sharding.over_local_devices`);
  objects draw their own keys, so the tables equal one device's. An odd batch (3) is
  padded to split evenly (4, the batch of the one-device run)."""
  kw = dict(samples=SAMPLES, batch_size=3, max_objects=8, refine=True, progress=False)
  one = evaluation.evaluate(tiny_run[0], tiny_dataset, **{**kw, "batch_size": 4})
  out = str(tmp_path / "two.json")
  env = {**os.environ, "JAX_PLATFORMS": "cpu",
         "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
  done = subprocess.run([sys.executable, "-c", _TWO_DEVICES, tiny_run[0], tiny_dataset, out,
                         json.dumps(kw)], cwd=ROOT, env=env, capture_output=True, text=True,
                        timeout=900)
  assert done.returncode == 0, done.stderr[-3000:]
  with open(out) as f:
    two = json.load(f)
  assert two["batch_size"] == one["batch_size"] == 4
  assert two["f1"] == pytest.approx(one["f1"])
  assert set(two["table2"]) == set(one["table2"])
  for name, row in one["table2"].items():
    if name.endswith("+Refine"):  # LM through contacts amplifies float rounding that
      # depends on the compiled batch shape (one device alone: the same objects refined 4
      # or 2 at a time differ by up to 0.4 % in density), so only close, not equal
      for k in ("rmse", "mae"):
        assert two["table2"][name][k] == pytest.approx(row[k], rel=0.1), (name, k)
      continue
    for k in ("top1", "top5", "top10", "rmse", "mae"):
      assert two["table2"][name][k] == pytest.approx(row[k], rel=1e-3, abs=1e-3), (name, k)


def test_partial_records_round_trip_and_recompute_what_is_unreadable(tmp_path):
  saved = partial.PartialRecords(str(tmp_path), {"samples": 8})
  rec = {("blocks",): np.array([2, 3]), ("sweep", "PPD+Sample", 0.05, "top1"): np.ones(2)}
  saved.save(0, rec)
  back = saved.load(0)
  assert set(back) == set(rec) and np.array_equal(back[("blocks",)], [2, 3])
  assert saved.load(4) is None and saved.count() == 1
  with open(os.path.join(str(tmp_path), "batch-0000004.npz"), "wb") as f:
    f.write(b"truncated")
  assert saved.load(4) is None  # recomputed, not a crash
  with pytest.raises(partial.OtherEvaluation, match="samples"):
    partial.PartialRecords(str(tmp_path), {"samples": 16})
  # records saved before a setting existed ran as its default: they resume with it only
  partial.PartialRecords(str(tmp_path), {"samples": 8, "network_prior_weight": -1.0})
  with pytest.raises(partial.OtherEvaluation, match="network_prior_weight"):
    partial.PartialRecords(str(tmp_path), {"samples": 8, "network_prior_weight": 0.005})


def test_compacted_records_read_back_whole_and_resume_nothing(tmp_path):
  """`partial.compact` folds the batches into one compressed file that `saved_records`
  reads back equal; the batch files are gone, so an evaluation would recompute them;
  batches saved after it make the folder ambiguous until they are compacted in its place."""
  folder = str(tmp_path / "partial")
  store = partial.PartialRecords(folder, {"test": 1})
  for start in (0, 3):
    store.save(start, {("blocks",): np.arange(start, start + 3),
                       ("guess", "PPD"): np.full((3, 5), start, np.int32)})
  before = partial.saved_records(folder)
  path = partial.compact(folder)
  assert os.path.basename(path) == partial.RECORDS_FILE and store.count() == 0
  after = partial.saved_records(folder)
  assert set(after) == set(before)
  for k, v in before.items():
    np.testing.assert_array_equal(after[k], v)
  assert store.load(0) is None
  store.save(0, {("blocks",): np.arange(2), ("guess", "PPD"): np.zeros((2, 5), np.int32)})
  with pytest.raises(ValueError, match="both"):  # run again on it: which is whole?
    partial.saved_records(folder)
  partial.compact(folder)  # the finished rerun's batches replace the file
  assert len(partial.saved_records(folder)[("blocks",)]) == 2 and store.count() == 0
  with open(path, "wb") as f:
    f.write(b"not a zip")
  with pytest.raises(ValueError, match="cannot be read"):
    partial.saved_records(folder)


def test_intervals_note_says_what_was_resampled():
  """Results before the cluster bootstrap say objects; later ones name the geometries."""
  assert markdown.intervals_note({}) == "95 % bootstrap intervals over objects"
  note = markdown.intervals_note({"intervals_over": "geometries", "geometries": 300,
                                  "data_kind": "tools"})
  assert note.startswith("95 % bootstrap intervals over the 300 tools (each drawn with all")


def test_scores_by_material_count_metal_read_in_its_other_range():
  """Per material of the true box: top-1 and RMSE of the guesses; a metal box read in
  metal's other slot range (aluminium-like vs steel-like) is a range confusion."""
  slot = np.array([[4, 79, 24], [29, 74, -1]])  # 0-based: wood 4; metal 79, 24, 74; stone 29
  material = np.array([[0, 4, 4], [2, 4, -1]])  # wood, metal, metal / stone, metal
  guess = np.array([[4, 27, 78], [29, 74, 0]])
  out = tables.by_material(slot, slot >= 0, material, {"PPD": guess})["PPD"]
  assert out["wood"] == {"boxes": 1, "top1": 100.0, "rmse": 0.0}
  assert out["metal"]["boxes"] == 3 and out["metal"]["top1"] == pytest.approx(100 / 3)
  assert out["metal"]["rmse"] == pytest.approx(np.sqrt((52 ** 2 + 54 ** 2) / 3))
  assert out["range_confusions"] == pytest.approx(100 * 2 / 5)  # 79 -> 27 and 24 -> 78
