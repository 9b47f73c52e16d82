"""+Search on the look-alike video towers (issue 64): does a search that iterates the draw,
and candidates that carry inertia scales, reach the densities that +Sample misses?

  python experiments/video_search/run.py --model=WORKDIR --test_towers=ROOT/test_towers.npz \
      --variant=search:rounds=4,refine=True \
      --variant=shells:rounds=4,sample_inertia=True,refine=True --out=DIR
  python experiments/video_search/run.py --collect --val_towers=V/test_towers.npz \
      --val_baseline=V --runs=DIR --test_towers=T/test_towers.npz --test_runs=TDIR \
      --results=experiments/results/video_search.json

Each variant is the pipeline's evaluate step (`video_decompose.decompose_test`: the depth
fit, no screen) with the model's `eval` keys changed, run on the tracked trajectories of
every tower: DIR/NAME_refine.npz (refined) and DIR/NAME_sample.npz (the selection's winner
before refinement), and DIR/summary.json (the seconds each took). `--collect` reads the
variants' answers on validation beside the validation pipeline's own (+Sample and +Refine:
V/decompositions_{sample,refine}.npz) and, for the test towers, the pipeline's answers
made with each setting (TDIR/NAME_{sample,refine}.npz), and writes the rows with 95 %
bootstrap intervals over towers, the variant of least refined RMSE on validation as
"chosen", and with --baseline each variant's RMSE paired against it. --section puts a
later question's rows under their own key (the report reads the study's latest choice).
"""

from __future__ import annotations

import json
import os
import sys
import time

from absl import app, flags

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import numpy as np  # noqa: E402

from ppdjax.metrics import bootstrap_interval  # noqa: E402
from ppdjax.reproduce import video_decompose, video_report  # noqa: E402
from ppdjax.training import checkpoints  # noqa: E402

flags.DEFINE_string("model", None, "The fine-tuned look-alike model (workdir or export).")
flags.DEFINE_string("test_towers", None, "A video pipeline's test_towers.npz.")
flags.DEFINE_multi_string("variant", [], "NAME:key=value,... (eval keys; value JSON).")
flags.DEFINE_string("out", None, "The folder for the answers and summary.json.")
flags.DEFINE_bool("collect", False, "Collect the runs' rows into --results.")
flags.DEFINE_string("val_towers", None, "--collect: the validation towers.")
flags.DEFINE_string("val_baseline", None, "--collect: the validation pipeline's root.")
flags.DEFINE_string("runs", None, "--collect: the variants' answers on validation.")
flags.DEFINE_string("test_runs", None, "--collect: the test pipeline's answers per variant.")
flags.DEFINE_string("results", None, "--collect: the results file.")
flags.DEFINE_string("section", "", "--collect: the results file's key for these rows ('': the "
                    "first question's, at the top level).")
flags.DEFINE_string("baseline", None, "--collect: the variant every other one is paired with.")
flags.DEFINE_string("machine", None, "--collect: where the decompositions ran (required).")
FLAGS = flags.FLAGS


def parse_variant(text: str) -> tuple[str, dict]:
  name, _, body = text.partition(":")
  changes = {}
  for item in filter(None, body.split(",")):
    key, _, value = item.partition("=")
    changes[key] = json.loads(value.lower() if value in ("True", "False") else value)
  return name, changes


def rows(test: dict, ev: dict, ways: tuple[str, ...]) -> dict:
  """The report's density rows (`video_report.summary`) of answers `ev` per trajectory."""
  blocks = test["valid"].sum(-1)
  out = {}
  for way in ways:
    ok = np.flatnonzero(ev[f"{way}_valid"].any(-1))
    out[way], _ = video_report.summary(test, ev, way, ok, blocks)
  return out


def runs_rows(test: dict, folder: str, ways: tuple[str, ...]) -> dict:
  """{NAME_refine: rows, NAME_sample: rows} of every answers file in `folder`."""
  return {os.path.splitext(f)[0]: rows(test, dict(np.load(os.path.join(folder, f))), ways)
          for f in sorted(os.listdir(folder)) if f.endswith(".npz")}


def paired(test: dict, first: dict, second: dict, way: str) -> dict:
  """second's RMSE (slots) minus first's over the towers both answered, with a 95 %
  interval over towers drawing both."""
  ok = np.flatnonzero(first[f"{way}_valid"].any(-1) & second[f"{way}_valid"].any(-1))
  one, two = (video_report.matched(test, ev, way)[0] for ev in (first, second))
  diff = lambda i: (video_report.rmse_slots(two, test, ok[i])  # noqa: E731
                    - video_report.rmse_slots(one, test, ok[i]))
  return {"towers": int(len(ok)), "rmse": diff(np.arange(len(ok))),
          "rmse_ci95": list(bootstrap_interval(diff, len(ok)))}


def paired_rows(test: dict, folder: str, ways: tuple[str, ...]) -> dict:
  """Each refined variant in `folder` against --baseline's, per trajectory read."""
  load = lambda name: dict(np.load(os.path.join(folder, f"{name}_refine.npz")))  # noqa: E731
  base = load(FLAGS.baseline)
  names = [f.removesuffix("_refine.npz") for f in sorted(os.listdir(folder))
           if f.endswith("_refine.npz") and f != f"{FLAGS.baseline}_refine.npz"]
  return {f"{name}_minus_{FLAGS.baseline}": {way: paired(test, base, load(name), way)
                                              for way in ways} for name in names}


def collect() -> dict:
  """The rows on both splits, the variant of least refined RMSE on validation (tracked) as
  "chosen", and with --baseline each variant paired against it."""
  val = dict(np.load(FLAGS.val_towers))
  found = {}
  if FLAGS.val_baseline:
    found = {f"pipeline_{v}": rows(val, dict(np.load(os.path.join(
        FLAGS.val_baseline, f"decompositions_{v}.npz"))), ("tracked",))
             for v in ("sample", "refine")}
  found.update(runs_rows(val, FLAGS.runs, ("tracked",)))
  # a variant's refined answers under its name, its winner before refinement beside
  named = {k.removesuffix("_refine").replace("_sample", "_before_refinement")
           if not k.startswith("pipeline_") else k: v["tracked"] for k, v in found.items()}
  test = dict(np.load(FLAGS.test_towers))
  variants = {k: v for k, v in named.items()
              if not k.startswith("pipeline_") and not k.endswith("_before_refinement")}
  out = {"validation": {"towers": int(len(val["valid"])), "rows": named},
         "test": {"towers": int(len(test["valid"])),
                  "rows": runs_rows(test, FLAGS.test_runs, ("tracked", "true"))},
         "chosen": min(variants, key=lambda k: np.nan_to_num(variants[k]["rmse_all"],
                                                             nan=np.inf))}
  if FLAGS.baseline:
    out["validation"]["paired"] = paired_rows(val, FLAGS.runs, ("tracked",))
    out["test"]["paired"] = paired_rows(test, FLAGS.test_runs, ("tracked", "true"))
  return out


def main(argv):
  del argv
  if FLAGS.collect:
    if not FLAGS.machine:
      raise app.UsageError("--collect needs --machine: where the decompositions ran")
    result = collect()
    result.update(command="python " + " ".join(sys.argv), machine=FLAGS.machine,
                  **({"baseline": FLAGS.baseline} if FLAGS.baseline else {}))
    previous = json.load(open(FLAGS.results)) if os.path.exists(FLAGS.results) else {}
    if FLAGS.section:
      previous[FLAGS.section] = result
    else:
      previous.update(result)
    with open(FLAGS.results, "w") as f:
      json.dump(previous, f, indent=1)
    print("chosen on validation:", result["chosen"])
    for split in ("validation", "test"):
      for name, row in result[split]["rows"].items():
        row = row.get("tracked", row)
        print(split, name, *(f"{row.get(k, float('nan')):.1f}" for k in (
            "rmse_all", "rmse_2_blocks", "rmse_3_blocks", "rmse_4_blocks")))
    return
  os.makedirs(FLAGS.out, exist_ok=True)
  path = os.path.join(FLAGS.out, "summary.json")
  summary = json.load(open(path)) if os.path.exists(path) else {}
  for text in FLAGS.variant:
    name, changes = parse_variant(text)
    config = checkpoints.read_config(FLAGS.model)  # the model's own settings, then the changes
    config.eval.update(changes)
    start = time.time()
    video_decompose.decompose_test(
        config, FLAGS.model, FLAGS.test_towers,
        {v: os.path.join(FLAGS.out, f"{name}_{v}.npz") for v in ("sample", "refine")},
        ways=("tracked",))
    summary[name] = {"changes": changes, "seconds": time.time() - start}
    print(name, json.dumps(summary[name]), flush=True)
    with open(path, "w") as f:
      json.dump(summary, f, indent=1)


if __name__ == "__main__":
  flags.mark_flags_as_required(["test_towers"])
  app.run(main)
