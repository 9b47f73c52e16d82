"""Closed-loop pushes: does choosing each push by its information gain beat the paper's four?

  # the loop on validation and test towers of fresh seeds (simulation-heavy: an accelerator)
  python experiments/active_pushes/run.py record --prior_model=DIR --setting=depth \
      --data=out/tau_val --split=val --objects=160 --out=out/active_val_depth.npz
  python experiments/active_pushes/run.py record --prior_model=DIR --setting=depth \
      --data=out/post_test --split=test --objects=160 --out=out/active_test_depth.npz
  # accuracy and interval width by pushes made, paired intervals, the plot
  python experiments/active_pushes/run.py report --val_records=out/active_val_depth.npz \
      --records=out/active_test_depth.npz --out=experiments/results/posterior.json

`record` takes each tower's boxes and density scores from `make_decompose_fn(PRIOR_MODEL,
SETTINGS[setting]())` (boxes fitted to the voxels and the image, or to the voxels and the
depth image; the scores of a model that reads no trajectory, so that the prior knows none
of the pushes), draws the `--samples`
candidate assignments +Sample would, and simulates them and the true tower under each of the
64 candidate pushes (`ppdjax.candidate_pushes()`) over the selection's horizon. Then, with
the same candidates throughout, three policies make up to four pushes: the paper's four in
order (fixed), four distinct random ones (random), and active: the paper's first, then each
next push the one of largest expected information gain (`infer.active.information_gain`,
the public `next_push`'s formula) over the posterior's top `--hypotheses`. After each push
the tower is decomposed again: the closest candidate over the pushes made (the paper's
+Sample) and the posterior over them (`infer.posterior.density_posterior`, the paper
setting's power). The posterior's temperature (one scale over the closest distance, for
every box count) was calibrated for a network that reads the four pushes; with this prior
it is chosen again: the loop runs at each of `--scales`, and `report` takes the one whose
fixed four pushes' 90 % intervals cover closest to 90 % on the validation towers, then
pairs the policies on the test towers.
"""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from tqdm import tqdm

import ppdjax
from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS, OBS_KEYS, density_to_slot
from ppdjax.infer import active, posterior, refine, sampling
from ppdjax.infer.config import DecomposeConfig
from ppdjax.primitives import bottom_to_top, bottom_to_top_order
from ppdjax.report.provenance import read_provenance, write_provenance
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import jax_engine, simulate

try:  # run as a script (its folder on the path) or imported by the tests (as a package)
  import refine_loop
except ImportError:
  from active_pushes import refine_loop

FLAGS = flags.FLAGS
POLICIES = ("fixed", "random", "active")
REFINED = "_refined"  # a policy's answers refined after each push (refine_loop)
MAX_PUSHES = 4
# The prior's boxes: the paper's inputs (voxels and image), or the depth image
# (`DecomposeConfig.best()` without its screening and refinement, which read the paper's four
# pushes' motion; the loop must see only the pushes it made).
SETTINGS = {
    "paper_inputs": DecomposeConfig.paper,
    "depth": lambda: DecomposeConfig.best().replace(
        **{"select.screen_steps": 0, "select.horizon": 32, "refine.enabled": False}),
}


def closed_loop(sims, distances, slots, distinct, logp, valid, key, *, paper, scale, power,
                hypotheses):
  """One tower: for each policy and each count of pushes made (1..4), the closest
  candidate's slots and the posterior's 90 % interval; and the pushes each policy made.

  sims (S, N, T, 7) candidates under the N pushes; distances (S, N) each to the truth's."""
  n = distances.shape[1]
  # the distance over the pushes made so far (done (N,) bool), as +Sample's over its pushes
  over = lambda done: jnp.sum(jnp.where(done, distances, 0.0), -1) / jnp.sum(done)  # noqa: E731

  def decompose_with(done):
    d = over(done)
    answer = slots[jnp.argmin(jnp.where(distinct, d, jnp.inf))]
    post = posterior.density_posterior(slots, d, logp, valid, scale=scale, level=0.9,
                                       identified_width=0, distinct_S=distinct,
                                       prior_power=power)
    return answer, post.lower, post.upper

  def run(order_fn):
    done, made, rows = jnp.zeros(n, bool), [], []
    for k in range(MAX_PUSHES):
      nxt = order_fn(k, done)
      done = done.at[nxt].set(True)
      made.append(nxt)
      rows.append(decompose_with(done))
    return [jnp.stack(x) for x in zip(*rows)], jnp.stack(made)

  random = jax.random.permutation(key, n)

  def active_next(k, done):
    if k == 0:
      return paper[0]
    w, t = posterior.candidate_weights(over(done), logp, valid, scale=scale,
                                       distinct_S=distinct, prior_power=power)
    top_w, top = jax.lax.top_k(w, hypotheses)
    gain = active.information_gain(sims[top], jax.nn.softmax(top_w), t)
    return jnp.argmax(jnp.where(done, -jnp.inf, gain))

  out = {}
  for name, fn in (("fixed", lambda k, done: paper[k]), ("random", lambda k, done: random[k]),
                   ("active", active_next)):
    (answer, lower, upper), made = run(fn)
    out[name] = {"answer": answer, "lower": lower, "upper": upper, "pushes": made}
  return out


def record(prior_model: str, setting: str, data: str, split: str, objects: int, batch: int,
           samples: int, hypotheses: int, seed: int, scales: tuple[float, ...],
           refine_scale: float | None, refine_weights: tuple[float, ...], out: str) -> None:
  ds = ppdjax.open_dataset(data, split)
  n = len(ds) if objects <= 0 else min(objects, len(ds))
  config = SETTINGS[setting]()
  decompose = ppdjax.make_decompose_fn(prior_model, config)
  pushes = ppdjax.candidate_pushes()
  paper = jnp.asarray(active.paper_push_indices(pushes, default_pushes()))
  steps = config.select.horizon
  power = config.posterior.prior_power
  # the depth preset's refinement (LM by forward differences) through the JAX engine
  refinement, refine_settings = DecomposeConfig.best().refine, jax_engine(decompose.settings)
  if refine_scale is not None and refine_scale not in scales:
    raise ValueError(f"--refine_scale {refine_scale} is not among --scales {scales}")
  traj_steps = ds.take(np.arange(1))["trajectories"].shape[-2]  # the whole trajectories

  def one(prims, logits, true, key):
    slots, distinct = sampling.candidate_slots(logits[:, :NUM_DENSITY_SLOTS], prims.valid,
                                               samples, key)
    logp = sampling.log_prior(logits, slots, prims.valid)
    observed = simulate(true, pushes, steps=steps, settings=decompose.settings)  # (N, T, 7)
    sims = simulate(sampling.with_slots(prims, slots), pushes, steps=steps,
                    settings=decompose.settings)  # (S, N, T, 7)
    distances = jax.vmap(jax.vmap(lambda a, b: metrics.trajectory_distance(
        a[None], b[None]), (0, 0)), (0, None))(sims, observed)  # (S, N)
    loops = [closed_loop(sims, distances, slots, distinct, logp, prims.valid,
                         jax.random.fold_in(key, 1), paper=paper, scale=scale, power=power,
                         hypotheses=hypotheses) for scale in scales]
    refined = {}
    if refine_scale is not None:  # each policy's answers refined on its pushes made
      at = loops[scales.index(refine_scale)]
      whole = simulate(true, pushes, steps=traj_steps, settings=refine_settings)  # (N, T, 7)
      prior = (refine.density_prior(logits[:, :NUM_DENSITY_SLOTS])
               if max(refine_weights) > 0 else None)  # the look's densities (MAP)

      def at_weight(w):  # (P, M, K) answers, (P, M) kept, one prior weight
        return jax.vmap(lambda a, m: refine_loop.refine_made(
            prims, a, m, whole, pushes, steps=refinement.steps, jacobian=refinement.jacobian,
            settings=refine_settings, prior=prior, prior_weight=w))(
                jnp.stack([at[p]["answer"] for p in POLICIES]),
                jnp.stack([at[p]["pushes"] for p in POLICIES]))
      answers, closer = jax.vmap(at_weight)(jnp.asarray(refine_weights, jnp.float32))
      refined = {f"{p}_refined": {"answer": answers[:, i], "closer": closer[:, i]}
                 for i, p in enumerate(POLICIES)}  # (W, M, K) and (W, M) per tower
    loops = jax.tree.map(lambda *x: jnp.stack(x), *loops)  # leading axis: the scales
    loops.update(refined)
    # the reference no policy of four pushes is expected to pass: the closest candidate
    # over all the candidate pushes
    loops["all"] = {"answer": slots[jnp.argmin(jnp.where(distinct, distances.mean(-1),
                                                         jnp.inf))]}
    return loops

  loop = jax.jit(jax.vmap(one))
  keep: dict[str, list] = {"true": [], "valid": [], "materials": []}
  start = time.time()
  for lo in tqdm(range(0, n, batch), desc="closed loop", unit="batch"):
    sample = ds.take(np.arange(lo, min(lo + batch, n)))
    res = decompose({k: sample[k] for k in OBS_KEYS + config.fit.with_},
                    jax.random.key(seed + lo))
    keys = jax.random.split(jax.random.key(seed + 1 + lo), len(sample["image"]))
    rows = loop(res.primitives, res.density_logits, sample["primitives"], keys)
    order = np.asarray(bottom_to_top_order(res.primitives))  # pair boxes bottom to top
    take = lambda x: np.take_along_axis(  # noqa: E731
        np.asarray(x), order.reshape(order.shape[:1] + (1,) * (np.ndim(x) - 2)
                                     + order.shape[1:]), -1)
    for name, r in rows.items():
      for field in set(r) & {"answer", "lower", "upper"}:
        keep.setdefault(f"{name}_{field}", []).append(take(r[field]))
      for field in set(r) & {"pushes", "closer"}:
        keep.setdefault(f"{name}_{field}", []).append(np.asarray(r[field]))
    true = jax.tree.map(np.asarray, bottom_to_top(jax.tree.map(jnp.asarray,
                                                               sample["primitives"])))
    keep["true"].append(np.where(true.valid, density_to_slot(true.density), -1))
    keep["valid"].append(take(res.primitives.valid))
    keep["materials"].append(np.asarray(sample["materials"]))
  arrays = {k: np.concatenate(v) for k, v in keep.items()}
  np.savez_compressed(out, seconds=time.time() - start, setting=setting, data=data,
                      split=split,
                      prior_model=prior_model, samples=samples, hypotheses=hypotheses,
                      scales=np.asarray(scales), power=power,
                      refine_scale=np.nan if refine_scale is None else refine_scale,
                      refine_weights=np.asarray(refine_weights),
                      **arrays)
  print(f"{n} towers in {time.time() - start:.0f} s -> {out}")


def refine_weights_of(rec) -> np.ndarray:
  """The prior weights a record was refined at ([0] before they were recorded)."""
  return np.asarray(rec["refine_weights"] if "refine_weights" in rec else [0.0])


def by_weight(rec, key: str) -> np.ndarray:
  """A refined field with its prior-weight axis (towers, W, ...): records refined at one
  weight (before the axis was recorded) have W = 1."""
  a = rec[key]
  return a[:, None] if "refine_weights" not in rec else a


def scores(rec, policy: str, k: int, scale: int, weight: int = 0, clip: bool = False) -> dict:
  """Per tower (towers whose box count is the truth's): exact boxes, squared slot errors,
  interval widths and coverage after k pushes (1-based), the posterior at the scale of
  index `scale` (its choices of push too). Policy "all": the closest over every candidate
  push (no interval: its width is one slot). A refined policy: its answers at the prior
  weight of index `weight`, with `clip` held inside the candidates' 90 % interval."""
  valid, true = rec["valid"], rec["true"]
  same = valid.sum(-1) == (true >= 0).sum(-1)
  if policy == "all":
    a = lo = hi = rec["all_answer"]
  elif policy.endswith(REFINED):  # the refined answer; the candidates' interval
    a = by_weight(rec, f"{policy}_answer")[:, weight, k - 1]
    lo, hi = (rec[f"{policy[:-len(REFINED)]}_{f}"][:, scale, k - 1] for f in ("lower", "upper"))
    a = np.clip(a, lo, hi) if clip else a
  else:
    a, lo, hi = (rec[f"{policy}_{f}"][:, scale, k - 1] for f in ("answer", "lower", "upper"))
  m = valid & same[:, None]
  return {"exact": np.where(m, a == true, 0).sum(-1), "sq": np.where(m, (a - true) ** 2.0, 0
                                                                      ).sum(-1),
          "width": np.where(m, hi - lo + 1, 0).sum(-1),
          "inside": np.where(m, (lo <= true) & (true <= hi), 0).sum(-1),
          "boxes": m.sum(-1), "same": same}


def summary(s: dict, towers: np.ndarray) -> dict:
  stat = {"top1": lambda i: 100.0 * s["exact"][i].sum() / s["boxes"][i].sum(),
          "rmse": lambda i: float(np.sqrt(s["sq"][i].sum() / s["boxes"][i].sum())),
          "width": lambda i: float(s["width"][i].sum() / s["boxes"][i].sum()),
          "coverage_90": lambda i: float(s["inside"][i].sum() / s["boxes"][i].sum())}
  out = {k: float(f(towers)) for k, f in stat.items()}
  for k, f in stat.items():
    out[f"{k}_ci95"] = list(metrics.bootstrap_interval(lambda i, f=f: f(towers[i]),
                                                       len(towers)))
  return out


def paired(first: dict, second: dict, towers: np.ndarray) -> dict:
  """second − first, top-1 and RMSE, 95 % intervals over towers drawing both."""
  def diff(i, key):
    t = towers[i]
    b = first["boxes"][t].sum()
    if key == "top1":
      return 100.0 * (second["exact"][t].sum() - first["exact"][t].sum()) / b
    return float(np.sqrt(second["sq"][t].sum() / b) - np.sqrt(first["sq"][t].sum() / b))
  return {key: list(metrics.bootstrap_interval(lambda i, key=key: diff(i, key), len(towers)))
          for key in ("top1", "rmse")}


def policy_rows(curves: dict, towers: np.ndarray) -> dict:
  """The results file's rows of one way to decompose: fixed four, random four, active two
  and four, their paired differences, and every policy by pushes made."""
  c = curves
  return {"fixed4": summary(c["fixed"][3], towers), "random4": summary(c["random"][3], towers),
          "active2": summary(c["active"][1], towers), "active4": summary(c["active"][3], towers),
          "paired": {"active2_minus_fixed4": paired(c["fixed"][3], c["active"][1], towers),
                     "active2_minus_fixed2": paired(c["fixed"][1], c["active"][1], towers),
                     "active4_minus_fixed4": paired(c["fixed"][3], c["active"][3], towers),
                     "active4_minus_random4": paired(c["random"][3], c["active"][3], towers)},
          "by_pushes": {p: [summary(x, towers) for x in c[p]] for p in POLICIES}}


def report(val_records: str, records: str, out: str) -> None:
  """Writes the results file's "active_by_setting"[the records' setting] and "active" (the
  depth setting's where it is measured, else the paper inputs'), and the plot."""
  val, rec = np.load(val_records), np.load(records)
  setting = str(rec["setting"]) if "setting" in rec else "paper_inputs"
  # the temperature whose fixed four pushes' 90 % intervals cover closest to 90 % (validation)
  val_cover = []
  for i in range(len(val["scales"])):
    c = scores(val, "fixed", MAX_PUSHES, i)
    val_cover.append(float(c["inside"][c["same"]].sum() / c["boxes"][c["same"]].sum()))
  chosen = int(np.argmin(np.abs(np.asarray(val_cover) - 0.9)))
  curves = {p: [scores(rec, p, k, chosen) for k in range(1, MAX_PUSHES + 1)]
            for p in POLICIES}
  towers = np.flatnonzero(curves["fixed"][0]["same"])
  active_result = policy_rows(curves, towers)
  refined = None
  if f"fixed{REFINED}_answer" in rec:
    for name, r in (("test", rec), ("validation", val)):
      if f"fixed{REFINED}_answer" not in r:
        raise ValueError(f"the {name} records are not refined: record both with refinement")
      if not np.isclose(r["refine_scale"], val["scales"][chosen]):
        raise ValueError(f"the {name} records refine the loop at temperature "
                         f"{r['refine_scale']}; validation chose {val['scales'][chosen]}: "
                         f"record again with --refine_scale={val['scales'][chosen]}")
    # the prior weight whose refined fixed four read the lowest RMSE on validation
    val_weights = refine_weights_of(val)
    val_rmse = []
    for w in range(len(val_weights)):
      c = scores(val, "fixed" + REFINED, MAX_PUSHES, chosen, w)
      val_rmse.append(float(np.sqrt(c["sq"][c["same"]].sum() / c["boxes"][c["same"]].sum())))
    weights = refine_weights_of(rec)
    at = np.flatnonzero(np.isclose(weights, val_weights[int(np.argmin(val_rmse))]))
    if len(at) == 0:
      raise ValueError(f"validation chose the prior weight "
                       f"{val_weights[int(np.argmin(val_rmse))]}, which the test records "
                       f"({weights.tolist()}) were not refined at")
    w = int(at[0])
    curves_at = lambda clip: {p: [scores(rec, p + REFINED, k, chosen, w, clip)  # noqa: E731
                                  for k in range(1, MAX_PUSHES + 1)] for p in POLICIES}
    refined = {**policy_rows(curves_at(False), towers),
               "kept_share": {p: [float(by_weight(rec, f"{p}{REFINED}_closer")[towers, w,
                                                                              k].mean())
                                  for k in range(MAX_PUSHES)] for p in POLICIES},
               "prior_weight": float(weights[w]),
               "validation_fixed4_rmse_by_weight": dict(zip(map(str, val_weights.tolist()),
                                                            val_rmse)),
               # held inside the candidates' 90 % interval (a rule read off the first refined
               # run's records, validation and test, and so measured on fresh towers since)
               "clipped": policy_rows(curves_at(True), towers)}
  active_result.update({
      "all_pushes": ({k: v for k, v in summary(scores(rec, "all", 0, 0), towers).items()
                      if k.startswith(("top1", "rmse"))} if "all_answer" in rec else None),
      "setting": setting,
      "towers": int(len(towers)), "boxes": int(curves["fixed"][0]["boxes"][towers].sum()),
      "towers_skipped_box_count": int(len(rec["valid"]) - len(towers)),
      "prior_model": str(rec["prior_model"]), "samples": int(rec["samples"]),
      "hypotheses": int(rec["hypotheses"]), "prior_power": float(rec["power"]),
      "scale": float(rec["scales"][chosen]),
      "validation_fixed4_coverage_by_scale": dict(zip(map(str, val["scales"].tolist()),
                                                      val_cover)),
      "validation_towers": int(len(val["valid"])),
      "pushes_chosen": {p: np.bincount(rec[f"{p}_pushes"][towers, chosen].ravel(),
                                       minlength=64).tolist() for p in ("active", "random")},
      "refined": refined,
      "command": ("python experiments/active_pushes/run.py report "
                  f"--val_records={val_records} --records={records}")})
  result = {}
  if os.path.exists(out):
    with open(out) as f:
      result = json.load(f)
  result.setdefault("active_by_setting", {})[setting] = active_result
  by_setting = result["active_by_setting"]
  # the depth setting's +Sample loop (its refined loop is a study: "refined", README)
  result["active"] = by_setting.get("depth", by_setting.get("paper_inputs"))
  plot({**active_result["by_pushes"],
        **{p + REFINED: rows for p, rows in (refined or {}).get("by_pushes", {}).items()}},
       f"{os.path.splitext(out)[0]}_active_{setting}.png")
  made_by = [result.get("command")] + [r["command"] for r in by_setting.values()]
  write_provenance(out, command="; ".join(c for c in made_by if c))  # calibration's, each loop's
  active_result["commit"] = read_provenance(out).get("commit")
  with open(out, "w") as f:
    json.dump(result, f, indent=1)
  print(json.dumps({k: v for k, v in active_result.items() if k != "by_pushes"}, indent=1)[:3000])


def plot(by_pushes: dict, path: str) -> None:
  """Top-1, RMSE and interval width against the number of pushes made, per policy."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  fig, axes = plt.subplots(1, 3, figsize=(11, 3.4))
  x = np.arange(1, MAX_PUSHES + 1)
  for ax, key, label in zip(axes, ("top1", "rmse", "width"),
                            ("density top-1 (%)", "density RMSE (slots)",
                             "90 % interval width (slots)")):
    for i, (p, rows) in enumerate(by_pushes.items()):
      if key == "width" and p.endswith(REFINED):  # the candidates' intervals: the same
        continue
      y = [r[key] for r in rows]
      lo, hi = zip(*[r[f"{key}_ci95"] for r in rows])
      ax.errorbar(x + 0.05 * (i - 1), y, yerr=[np.subtract(y, lo), np.subtract(hi, y)],
                  marker="o", capsize=3, label=p, color=f"C{POLICIES.index(p.split('_')[0])}",
                  linestyle="--" if p.endswith(REFINED) else "-")
    ax.set(xlabel="pushes made", ylabel=label, xticks=x)
  axes[0].legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=110)


def define_flags():
  """This study's flags, defined when it runs (not when a test imports it)."""
  flags.DEFINE_enum("mode", "record", ["record", "report"], "What to do (or the first argument).")
  flags.DEFINE_string("prior_model", "", "record: a model that reads no trajectory.")
  flags.DEFINE_enum("setting", "paper_inputs", list(SETTINGS), "record: the prior's boxes.")
  flags.DEFINE_string("data", "", "record: the dataset folder.")
  flags.DEFINE_string("split", "test", "record: the split.")
  flags.DEFINE_integer("objects", 0, "record: the first N objects (0: all).")
  flags.DEFINE_integer("batch", 8, "record: objects per call.")
  flags.DEFINE_integer("samples", 512, "record: candidate assignments per tower.")
  flags.DEFINE_integer("hypotheses", 32, "record: the posterior's top assignments for the gain.")
  flags.DEFINE_integer("seed", 0, "record: candidates' and random pushes' key.")
  flags.DEFINE_list("scales", ["0.01", "0.03", "0.1", "0.3", "1", "3"], "record: the posterior's "
                    "temperatures over the closest distance tried (one is chosen on validation).")
  flags.DEFINE_float("refine_scale", 1.0, "record: the temperature (one of --scales) whose "
                     "loop is also refined after each push (0: no refinement).")
  flags.DEFINE_list("refine_prior_weights", ["0"], "record: the MAP step's prior weights "
                    "tried (0 alone: least squares, kept where closer; with any weight above "
                    "0 every step is kept where its cost fell, weight 0's too); one is chosen "
                    "on validation.")
  flags.DEFINE_string("val_records", "", "report: the validation towers' record file.")
  flags.DEFINE_string("records", "", "report: the test towers' record file.")
  flags.DEFINE_string("out", "", "record: the .npz; report: the results .json (its 'active').")


def main(argv):
  mode = argv[1] if len(argv) > 1 else FLAGS.mode
  if mode == "record":
    record(FLAGS.prior_model, FLAGS.setting, FLAGS.data, FLAGS.split, FLAGS.objects,
           FLAGS.batch, FLAGS.samples, FLAGS.hypotheses, FLAGS.seed,
           tuple(map(float, FLAGS.scales)),
           FLAGS.refine_scale if FLAGS.refine_scale > 0 else None,
           tuple(map(float, FLAGS.refine_prior_weights)), FLAGS.out)
  else:
    report(FLAGS.val_records, FLAGS.records, FLAGS.out)


if __name__ == "__main__":
  define_flags()
  app.run(main)
