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
setting's power). With refinement, `--design_horizons` add loops that choose each next push
on the refined answer instead (`design.py`; every policy is refined, and `report` takes
the choosing policy of least refined RMSE on validation for "active"). The posterior's
temperature (one scale over the closest distance, for every box count) was calibrated for
a network that reads the four pushes; with this prior it is chosen again: the loop runs
at each of `--scales`, and `report` takes the one whose fixed four pushes' 90 % intervals
cover closest to 90 % on the validation towers, then pairs the policies on the test
towers.
"""

from __future__ import annotations

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
from ppdjax.sim.pushes import default_pushes
from ppdjax.sim.rollout_mjx import jax_engine, simulate

try:  # run as a script (its folder on the path) or imported by the tests (as a package)
  import design
  import refine_loop
  from report import DESIGN, MAX_PUSHES, POLICIES, REFINED, report
except ImportError:
  from active_pushes import design, refine_loop
  from active_pushes.report import DESIGN, MAX_PUSHES, POLICIES, REFINED, report

FLAGS = flags.FLAGS
# The prior's boxes: the paper's inputs (voxels and image), or the depth image
# (`DecomposeConfig.best()` without its screening and refinement, which read the paper's four
# pushes' motion; the loop must see only the pushes it made).
SETTINGS = {
    "paper_inputs": DecomposeConfig.paper,
    "depth": lambda: DecomposeConfig.best().replace(
        **{"select.screen_steps": 0, "select.horizon": 32, "refine.enabled": False}),
}


def closed_loop(sims, distances, slots, distinct, logp, valid, key, *, paper, scale, power,
                hypotheses, given=None):
  """One tower: for each policy and each count of pushes made (1..4), the closest
  candidate's slots and the posterior's 90 % interval; and the pushes each policy made.

  sims (S, N, T, 7) candidates under the N pushes; distances (S, N) each to the truth's;
  `given`: {policy: (4,) pushes} made by policies of their own (`design.design_loop`),
  decomposed alike."""
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
                   ("active", active_next),
                   *((p, lambda k, done, o=o: o[k]) for p, o in (given or {}).items())):
    (answer, lower, upper), made = run(fn)
    out[name] = {"answer": answer, "lower": lower, "upper": upper, "pushes": made}
  return out


def record(prior_model: str, setting: str, data: str, split: str, objects: int, batch: int,
           samples: int, hypotheses: int, seed: int, scales: tuple[float, ...],
           refine_scale: float | None, refine_weights: tuple[float, ...],
           design_horizons: tuple[int, ...], out: str) -> None:
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
  if design_horizons and (refine_scale is None or tuple(refine_weights) != (0.0,)):
    raise ValueError("--design_horizons choose pushes on the refined answer (least squares): "
                     "they need --refine_scale and --refine_prior_weights=0")
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
    whole = None if refine_scale is None else simulate(  # (N, T, 7)
        true, pushes, steps=traj_steps, settings=refine_settings)
    designs = {f"{DESIGN}{h}": design.design_loop(  # pushes chosen on refined answers
        prims, slots, distinct, distances, whole, pushes, paper[0],
        pushes_made=MAX_PUSHES, horizon=h, steps=refinement.steps,
        jacobian=refinement.jacobian, settings=refine_settings) for h in design_horizons}
    loops = [closed_loop(sims, distances, slots, distinct, logp, prims.valid,
                         jax.random.fold_in(key, 1), paper=paper, scale=scale, power=power,
                         hypotheses=hypotheses,
                         given={p: d["pushes"] for p, d in designs.items()})
             for scale in scales]
    refined = {f"{p}{REFINED}": {"answer": d["refined_answer"][None],  # one weight: 0
                                 "closer": d["refined_closer"][None]}
               for p, d in designs.items()}
    if refine_scale is not None:  # each policy's answers refined on its pushes made
      at = loops[scales.index(refine_scale)]
      prior = (refine.density_prior(logits[:, :NUM_DENSITY_SLOTS])
               if max(refine_weights) > 0 else None)  # the look's densities (MAP)

      def at_weight(w):  # (P, M, K) answers, (P, M) kept, one prior weight
        return jax.vmap(lambda a, m: refine_loop.refine_made(
            prims, a, m, whole, pushes, steps=refinement.steps, jacobian=refinement.jacobian,
            settings=refine_settings, prior=prior, prior_weight=w))(
                jnp.stack([at[p]["answer"] for p in POLICIES]),
                jnp.stack([at[p]["pushes"] for p in POLICIES]))
      answers, closer = jax.vmap(at_weight)(jnp.asarray(refine_weights, jnp.float32))
      refined.update({f"{p}_refined": {"answer": answers[:, i], "closer": closer[:, i]}
                      for i, p in enumerate(POLICIES)})  # (W, M, K) and (W, M) per tower
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
                      design_horizons=np.asarray(design_horizons, np.int32),
                      **arrays)
  print(f"{n} towers in {time.time() - start:.0f} s -> {out}")


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
  flags.DEFINE_list("design_horizons", ["64", "256"], "record: a loop that chooses each next "
                    "push on the refined answer (Laplace posterior, A-optimal in slots) for "
                    "each of these horizons (steps of the candidate pushes' motion it weighs; "
                    "empty: none); one policy is chosen on validation.")
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
           tuple(map(float, FLAGS.refine_prior_weights)),
           tuple(int(h) for h in FLAGS.design_horizons), FLAGS.out)
  else:
    report(FLAGS.val_records, FLAGS.records, FLAGS.out)


if __name__ == "__main__":
  define_flags()
  app.run(main)
