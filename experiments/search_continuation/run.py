"""Does +Search find look-alike towers' densities better when its early rounds weigh only the
strike's first steps (`select.continuation`), or when refinement starts from several of its
closest candidates (`refine.starts`)? A proxy that runs on a CPU.

  python experiments/search_continuation/run.py --towers=16 --continuations=0,16,32 \
      --out=experiments/results/search_continuation.json
  python experiments/search_continuation/run.py --towers=16 --continuations=0 \
      --starts=1,4,8 --out=experiments/results/search_starts.json

The proxy keeps what the search itself faces and drops the rest: look-alike towers of the
video preset's generator (2, 3 and 4 blocks, `--towers` of each, half the blocks hollow:
`dataset.hollow`), their true boxes (no fit), their true trajectories under the pendulum
strike (no video, no tracking) and density scores that say nothing (uniform: painted blocks;
the fine-tuned model's scores are not used). Each tower is searched as the look-alike preset
searches (`search.search_densities`: rounds of 512 candidates with inertia scales, on the
engine `decompose` picks: MuJoCo C on a CPU), once per continuation, from the same key,
then refined by `decompose`'s rule (`refine_if_closer` from the candidate closest over the
whole trajectory, on the data's box-plane JAX engine, with forward differences: forward
mode over eight starts ran out of a 2-core machine's 24 GB), or from each of the `--starts`
closest distinct candidates, the refined answer of least distance kept (the selection of
`refine.refine_from_candidates`). Reported: density RMSE in slots by block count, before
and after refinement, the answers' trajectory distances, and paired differences against no
continuation and against one start (95 % intervals over towers).
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from ppdjax import metrics, primitives
from ppdjax.configs import video
from ppdjax.conventions import NUM_DENSITY_SLOTS, density_to_slot
from ppdjax.dataset import generation, hollow, towers
from ppdjax.infer import search
from ppdjax.infer.refine import refine_if_closer
from ppdjax.report.provenance import write_provenance
from ppdjax.sim.rollout_mjx import engine_settings, jax_engine, simulate

flags.DEFINE_integer("towers", 8, "Towers of each block count (2, 3, 4).")
flags.DEFINE_integer("seed", 2_000_011, "The towers' seed (never trained or tested on).")
flags.DEFINE_list("continuations", ["0", "16"], "select.continuation values (0: none).")
flags.DEFINE_integer("rounds", 8, "+Search's rounds (the look-alike preset's).")
flags.DEFINE_integer("samples", 512, "Candidates per round.")
flags.DEFINE_list("starts", ["1"], "Refine from the M closest distinct candidates and keep the "
                  "closest refined (M = 1: `decompose`'s one start); each M a row.")
flags.DEFINE_float("noise_mm", 0.0, "Gaussian noise on the observed positions, per axis (mm): "
                   "0.33 gives a median error of 0.5 mm, the tracker's.")
flags.DEFINE_string("out", "experiments/results/search_continuation.json", "Results file.")
FLAGS = flags.FLAGS


def lookalike_towers(seed: int, per_count: int):
  """Look-alike towers as the video preset draws them: (Primitives (N, K) with mean
  densities and inertia scales, block counts (N,))."""
  cfg = video.get_config("lookalike").data
  rng = np.random.default_rng(seed)
  prims, counts = [], []
  for blocks in cfg.block_counts:
    for _ in range(per_count):
      p, ids = towers.sample_configurations(rng, 1, num_blocks=blocks, rotate=cfg.rotate,
                                            size_noise=cfg.size_noise, material_set="real")
      p, _ = hollow.hollow_blocks(rng, p, ids, cfg.hollow)
      prims.append(jax.tree.map(lambda x: x[0], p))
      counts.append(blocks)
  return primitives.stack(prims), np.asarray(counts), cfg


def main(argv):
  del argv
  truth, counts, cfg = lookalike_towers(FLAGS.seed, FLAGS.towers)
  pushes = generation.pushes_of(cfg)
  # as `decompose` runs: candidates on the simulator "auto" picks (MuJoCo C on a CPU),
  # refinement and the observations on the data's JAX engine (box-plane)
  settings, refine_settings = engine_settings("auto", cfg.backend), jax_engine(cfg.backend)
  observed = jnp.asarray(simulate(truth, pushes, steps=cfg.steps, settings=refine_settings))
  if FLAGS.noise_mm > 0:  # as tracked: the positions off by the tracker's error, at random
    noise = 1e-3 * FLAGS.noise_mm * jax.random.normal(jax.random.key(FLAGS.seed),
                                                     observed[..., :3].shape)
    observed = observed.at[..., :3].add(noise)
  k = truth.valid.shape[-1]
  logits = jnp.zeros((k, NUM_DENSITY_SLOTS))  # scores that say nothing: the paint
  geometry = truth.replace(inertia_scale=None)  # the densities and shells to find
  true_slots = density_to_slot(np.asarray(truth.density))
  valid = np.asarray(truth.valid)
  starts = tuple(int(m) for m in FLAGS.starts)
  results = {"towers": int(len(counts)), "blocks_by_tower": counts.tolist(),
             "seed": FLAGS.seed, "rounds": FLAGS.rounds, "samples": FLAGS.samples,
             "starts": list(starts), "noise_mm": FLAGS.noise_mm, "by_continuation": {}}
  per_tower = {}
  for c in map(int, FLAGS.continuations):
    @jax.jit
    def one(p, o, key, c=c):
      sel = search.search_densities(p, logits, o, pushes, num_samples=FLAGS.samples,
                                    rounds=FLAGS.rounds, key=key, inertia=True,
                                    continuation=c, settings=settings)
      # the M closest distinct candidates, each refined; the closest refined kept among the
      # first m of them for each m of --starts (m = 1: `decompose`'s start and rule)
      order = jnp.argsort(jnp.where(sel.distinct, sel.scores, jnp.inf))[:max(starts)]
      ref = jax.vmap(lambda i: refine_if_closer(
          jax.tree.map(lambda x: x[i], sel.boxes), o, sel.scores[i], pushes, steps=12,
          jacobian="differences", settings=refine_settings))(order)
      best = [jnp.argmin(ref.distance[:m]) for m in starts]
      return (sel.density, jnp.stack([ref.primitives.density[b] for b in best]),
              sel.scores.min(), jnp.stack([ref.distance[b] for b in best]))

    start = time.time()
    rows = [one(jax.tree.map(lambda x, i=i: x[i], geometry), observed[i],
                jax.random.key(FLAGS.seed + i)) for i in range(len(counts))]
    found, refined, dist, ref_dist = (np.stack([np.asarray(r[j]) for r in rows])
                                      for j in range(4))
    seconds = time.time() - start
    named = [("sample", found)] + [("refine" if m == 1 else f"refine_best_of_{m}",
                                    refined[:, j]) for j, m in enumerate(starts)]
    err = {name: np.where(valid, density_to_slot(d) - true_slots, 0.0) ** 2
           for name, d in named}
    per_tower[c] = {name: (e.sum(-1), valid.sum(-1)) for name, e in err.items()}
    first = named[1][0]  # one start: `decompose`'s refinement
    rmse = lambda e, i: float(np.sqrt(e[i].sum() / valid[i].sum()))  # noqa: E731
    row = {"seconds": seconds}
    for name, e in err.items():  # towers drawn with replacement for the intervals
      row[name] = {"rmse": rmse(e, np.arange(len(counts))),
                   "rmse_ci95": list(metrics.bootstrap_interval(
                       lambda i, e=e: rmse(e, np.asarray(i)), len(counts))),
                   **{f"rmse_{b}": rmse(e, counts == b) for b in cfg.block_counts}}
    row["squared_error_by_tower"] = {name: e.sum(-1).tolist() for name, e in err.items()}
    row["minus_one_start_rmse_ci95"] = {
        name: list(metrics.bootstrap_interval(lambda i, e=e: rmse(e, np.asarray(i))
                                              - rmse(err[first], np.asarray(i)), len(counts)))
        for name, e in err.items() if name.startswith("refine_best_of")}
    row["distance_mm"] = {"sample_median": 1e3 * float(np.median(dist)),
                          **{f"{name}_median": 1e3 * float(np.median(ref_dist[:, j]))
                             for j, (name, _) in enumerate(named[1:])}}
    results["by_continuation"][str(c)] = row
    print(c, json.dumps(row), flush=True)
  base = per_tower.get(0)
  if base is not None:
    for c, t in per_tower.items():
      if c == 0:
        continue
      diffs = {}
      for name in [n for n in t if n in base]:
        def diff(i, name=name, t=t):
          sq0, n0 = (x[i].sum() for x in base[name])
          sq1, _ = (x[i].sum() for x in t[name])
          return float(np.sqrt(sq1 / n0) - np.sqrt(sq0 / n0))
        diffs[name] = list(metrics.bootstrap_interval(
            lambda i, diff=diff: diff(np.asarray(i)), len(counts)))
      results["by_continuation"][str(c)]["minus_none_rmse_ci95"] = diffs
  command = "python " + " ".join([os.path.relpath(__file__)] + sys.argv[1:])
  results["command"] = command
  os.makedirs(os.path.dirname(FLAGS.out) or ".", exist_ok=True)
  with open(FLAGS.out, "w") as f:
    json.dump(results, f, indent=1)
  write_provenance(FLAGS.out, command=command)
  print(json.dumps(results, indent=1))


if __name__ == "__main__":
  app.run(main)
