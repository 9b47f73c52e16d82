"""+Search on the look-alike video towers (issue 64): does a search that iterates the draw,
and candidates that carry inertia scales, reach the densities that +Sample misses?

  python experiments/video_search/run.py --model=WORKDIR --test_towers=ROOT/test_towers.npz \
      --variant=search:rounds=4 --variant=shells:rounds=4,sample_inertia=True --out=DIR

  python experiments/video_search/run.py --collect --val_towers=V/test_towers.npz \
      --val_baseline=V --runs=DIR --test_towers=T/test_towers.npz --test_runs=TDIR \
      --results=experiments/results/video_search.json

Each variant is the look-alike preset's decomposition (`video_decompose.decompose_test`'s
settings: the depth fit, no screen) with the given `eval` keys changed, run on the tracked
trajectories of every tower. Writes DIR/VARIANT.npz (the answers; `search_density`: the
selection's winner before refinement) and DIR/summary.json (RMSE in slots of the box nearest
each true block, by block count, before and after refinement; seconds). `--collect` reads
the variants' answers (RUNS/NAME.npz) beside the validation pipeline's own (+Sample and
+Refine: V/decompositions_{sample,refine}.npz) and, for the test towers, the pipeline's
decompositions made with each variant (TDIR/NAME_{sample,refine}.npz), and writes the
rows with 95 % bootstrap intervals over towers.
"""

from __future__ import annotations

import json
import os
import sys
import time

from absl import app, flags

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from ppdjax.conventions import slot_to_density  # noqa: E402
from ppdjax.dataset import camera, generation  # noqa: E402
from ppdjax.infer import sampling  # noqa: E402
from ppdjax.infer.config import DecomposeConfig  # noqa: E402
from ppdjax.infer.decompose import make_decompose_fn  # noqa: E402
from ppdjax.reproduce import video_report  # noqa: E402
from ppdjax.training import checkpoints  # noqa: E402

flags.DEFINE_string("model", None, "The fine-tuned look-alike model (workdir or export).")
flags.DEFINE_string("test_towers", None, "A video pipeline's test_towers.npz.")
flags.DEFINE_multi_string("variant", [], "NAME:key=value,... (eval keys; value JSON).")
flags.DEFINE_string("out", None, "The folder for the answers and summary.json.")
flags.DEFINE_integer("limit", 0, "> 0: the first N towers only (a smoke test).")
flags.DEFINE_bool("collect", False, "Collect the runs' rows into --results.")
flags.DEFINE_string("val_towers", None, "--collect: the validation towers.")
flags.DEFINE_string("val_baseline", None, "--collect: the validation pipeline's root.")
flags.DEFINE_string("runs", None, "--collect: the variants' answers on validation.")
flags.DEFINE_string("test_runs", None, "--collect: the test pipeline's answers per variant.")
flags.DEFINE_string("results", None, "--collect: the results file.")
FLAGS = flags.FLAGS


def parse_variant(text: str) -> tuple[str, dict]:
  name, _, body = text.partition(":")
  changes = {}
  for item in filter(None, body.split(",")):
    key, _, value = item.partition("=")
    changes[key] = json.loads(value.lower() if value in ("True", "False") else value)
  return name, changes


def settings_of(cfg, changes: dict) -> DecomposeConfig:
  e = cfg.eval.to_dict() if hasattr(cfg.eval, "to_dict") else dict(cfg.eval)
  e.update(changes)
  return DecomposeConfig.from_eval(e).replace(**{
      "fit.enabled": True, "fit.depth": True, "fit.image": False, "select.screen_steps": 0})


def rmse_by_blocks(test: dict, ev: dict, towers: np.ndarray) -> dict:
  pred, _ = video_report.matched(test, ev, "tracked")
  blocks = test["valid"].sum(-1)
  out = {"all": video_report.rmse_slots(pred, test, towers)}
  for k in np.unique(blocks[towers]):
    out[str(int(k))] = video_report.rmse_slots(pred, test, towers[blocks[towers] == k])
  return out


def run_variant(trained, test: dict, towers: np.ndarray, settings: DecomposeConfig,
                size: int, batch: int) -> tuple[dict, float]:
  fn = make_decompose_fn(trained, settings, camera=camera.camera_dict(size, size),
                         pushes=generation.pushes_of(trained[1].data))
  n, k = test["valid"].shape
  out = {f"tracked_{f}": np.full((n, k) + test[f].shape[2:], np.nan, np.float32)
         for f in ("pos", "half_size", "density")}
  out.update(tracked_valid=np.zeros((n, k), bool), tracked_score=np.full(n, np.nan),
             search_density=np.full((n, k), np.nan, np.float32),
             inertia_scale=np.ones((n, k), np.float32))
  start = time.time()
  for at in tqdm(range(0, len(towers), batch), desc="decompose"):
    chunk = towers[at:at + batch]
    padded = np.concatenate([chunk, np.full(batch - len(chunk), chunk[-1])])
    obs = {"voxels": test["voxels"][padded], "image": test["image"][padded],
           "depth": test["depth"][padded],
           "trajectories": test["tracked_trajectory"][padded][:, None]}
    res = jax.tree.map(lambda a: np.asarray(a)[:len(chunk)],
                       fn(obs, jax.random.key(int(chunk[0]))))
    p = res.primitives
    for f in ("pos", "half_size", "density"):
      out[f"tracked_{f}"][chunk] = getattr(p, f)
    out["tracked_valid"][chunk], out["tracked_score"][chunk] = p.valid, res.score
    if p.inertia_scale is not None:
      out["inertia_scale"][chunk] = p.inertia_scale
    tau = settings.select.tau(True)  # the selection objective, as decompose_test reads it
    winner = np.argmin(res.scores - tau * np.asarray(jax.vmap(sampling.log_prior)(
        res.density_logits, res.candidates, p.valid)), -1)
    out["search_density"][chunk] = slot_to_density(
        np.take_along_axis(res.candidates, winner[:, None, None], 1)[:, 0])
  return out, time.time() - start


def rows(test: dict, ev: dict, ways: tuple[str, ...] = ("tracked",)) -> dict:
  """The report's density rows (`video_report.summary`) of answers `ev` per trajectory."""
  blocks = test["valid"].sum(-1)
  out = {}
  for way in ways:
    ok = np.flatnonzero(ev[f"{way}_valid"].any(-1))
    row, _ = video_report.summary(test, ev, way, ok, blocks)
    out[way] = row
  return out


def collect() -> dict:
  val = dict(np.load(FLAGS.val_towers))
  result = {"validation": {"towers": int(len(val["valid"])), "rows": {}},
            "test": {"towers": None, "rows": {}}}
  for name in ("sample", "refine"):  # the pipeline's own: +Sample and +Refine
    ev = dict(np.load(os.path.join(FLAGS.val_baseline, f"decompositions_{name}.npz")))
    result["validation"]["rows"][f"pipeline_{name}"] = rows(val, ev)["tracked"]
  for path in sorted(os.listdir(FLAGS.runs)):
    name, ext = os.path.splitext(path)
    if ext != ".npz":
      continue
    ev = dict(np.load(os.path.join(FLAGS.runs, path)))
    result["validation"]["rows"][name] = rows(val, ev)["tracked"]
    result["validation"]["rows"][name + "_before_refinement"] = rows(
        val, dict(ev, tracked_density=ev["search_density"]))["tracked"]
  test = dict(np.load(FLAGS.test_towers))
  result["test"]["towers"] = int(len(test["valid"]))
  for path in sorted(os.listdir(FLAGS.test_runs)):
    name, ext = os.path.splitext(path)
    if ext == ".npz":
      result["test"]["rows"][name] = rows(test, dict(np.load(os.path.join(FLAGS.test_runs, path))),
                                          ("tracked", "true"))
  return result


def main(argv):
  del argv
  if FLAGS.collect:
    result = collect()
    previous = json.load(open(FLAGS.results)) if os.path.exists(FLAGS.results) else {}
    previous.update(result, command="python " + " ".join(sys.argv),
                    chosen="shells8", machine="one NVIDIA H200 (the decompositions)")
    with open(FLAGS.results, "w") as f:
      json.dump(previous, f, indent=1)
    for split in ("validation", "test"):
      for name, row in result[split]["rows"].items():
        row = row.get("tracked", row)
        print(split, name, *(f"{row.get(k, float('nan')):.1f}" for k in (
            "rmse_all", "rmse_2_blocks", "rmse_3_blocks", "rmse_4_blocks")))
    return
  trained = checkpoints.load(FLAGS.model)
  cfg = trained[1]
  test = dict(np.load(FLAGS.test_towers))
  towers = np.flatnonzero(np.isfinite(test["tracked_trajectory"]).all((1, 2)))
  if FLAGS.limit:
    towers = towers[:FLAGS.limit]
  os.makedirs(FLAGS.out, exist_ok=True)
  path = os.path.join(FLAGS.out, "summary.json")
  summary = json.load(open(path)) if os.path.exists(path) else {}
  for text in FLAGS.variant:
    name, changes = parse_variant(text)
    settings = settings_of(cfg, changes)
    out, seconds = run_variant(trained, test, towers, settings, int(cfg.data.image_size),
                               int(cfg.eval.batch_size))
    np.savez_compressed(os.path.join(FLAGS.out, f"{name}.npz"), **out)
    searched = dict(out, tracked_density=out["search_density"])
    summary[name] = {"changes": changes, "towers": int(len(towers)), "seconds": seconds,
                     "rmse": rmse_by_blocks(test, out, towers),
                     "rmse_before_refinement": rmse_by_blocks(test, searched, towers),
                     "settings": settings.to_dict()}
    print(name, json.dumps(summary[name]["rmse"]), json.dumps(
        summary[name]["rmse_before_refinement"]), f"{seconds:.0f} s", flush=True)
    with open(path, "w") as f:
      json.dump(summary, f, indent=1)


if __name__ == "__main__":
  flags.mark_flags_as_required(["test_towers"])
  app.run(main)
