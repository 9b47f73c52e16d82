"""+Sample on tools when the candidates are simulated at a fraction of their densities.

A tool's true boxes hold more volume than its parts (a median 1.29 times the tool's mass
with the parts' densities as labels; `tool_box_mass.py`), so the candidate whose
trajectory comes closest carries densities below the labels. Here every candidate is
simulated at `fill` × the densities of its slots (the fraction of a box its part fills,
learned on other tools: 1 / 1.298, the median over 100 tools of seed 8) while the slots
it is scored by stay the labels'. Both the network's boxes and the true boxes, on every
tool of a dataset the tools model never saw, each candidate simulated with MuJoCo C (the
engine the tools' own trajectories came from), the network's 512 samples per tool:

    python -m ppdjax.generate --config=ppdjax/configs/tools.py --config.seed=7 \
        --config.data.num_tools=200 --out=out/tools_s7
    python experiments/tool_fill_study.py --data=out/tools_s7 \
        --out=experiments/results/tool_fill_study

Writes OUT/results.json and OUT/README.md (top-1 / top-5 / top-10 / RMSE / MAE with 95 %
bootstrap intervals over tools, per boxes and fill).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from tqdm.auto import tqdm

from ppdjax import metrics
from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import storage
from ppdjax.infer import baselines, rows, sampling
from ppdjax.infer.groups import decode_groups
from ppdjax.infer.tables import PRIOR_WEIGHTS, intervals, np_metrics
from ppdjax.primitives import bottom_to_top
from ppdjax.sim.simulate import simulate
from ppdjax.training import checkpoints

CALIBRATED_FILL = 1 / 1.298  # tools_order_study/box_mass.json: "calibration" (seed 8)
SPLITS = ("train", "val", "test")


def load_all(data_dir: str) -> tuple[dict, object]:
  """Every sample of every split (none trained on: the dataset is of another seed)."""
  parts, ds = [], None
  for split in SPLITS:
    ds = storage.open_dataset(data_dir, split)
    parts.append(ds.take(np.arange(len(ds)), keys=OBS_KEYS + ("primitives",)))
  return jax.tree.map(lambda *x: np.concatenate(x), *parts), ds


def decode(workdir: str, batch: dict, chunk: int = 20) -> dict:
  """The network's boxes and logits, and the true boxes (bottom to top) with the network's
  k-th logits on the k-th (`groups.decode_groups`'s "true" group)."""
  model, _ = checkpoints.load(workdir)
  graphdef, state = nnx.split(model)
  fn = jax.jit(lambda s, o, t: decode_groups(graphdef, s, o, t, groups=(), camera=None,
                                             true_shapes=True))
  outs = []
  for i in range(0, len(batch["voxels"]), chunk):
    obs = {k: jnp.asarray(batch[k][i:i + chunk]) for k in OBS_KEYS}
    true = bottom_to_top(jax.tree.map(lambda x: jnp.asarray(x[i:i + chunk]),
                                      batch["primitives"]))
    d = fn(state, obs, true)
    outs.append(jax.device_get({"ppd": d["pred"], "true": d["fitted"]["true"],
                                "logits": d["logits"]}))
  return jax.tree.map(lambda *x: np.concatenate(x), *outs)


def score(boxes, slots, fill: float, observed, pushes) -> tuple[np.ndarray, np.ndarray]:
  """(distance (S,), MAE (S,)) of one object's candidates simulated at fill × density."""
  cands = sampling.with_slots(jax.tree.map(jnp.asarray, boxes), jnp.asarray(slots))
  cands = jax.tree.map(np.asarray, cands.replace(density=cands.density * fill))
  sim = simulate(cands, pushes, steps=observed.shape[-2], backend="mujoco")
  obs = np.asarray(observed, np.float64)
  return (np.asarray(metrics.trajectory_distance(sim, obs)),
          np.asarray(metrics.trajectory_mae(sim, obs)))


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--data", required=True, help="A tools dataset the model never saw.")
  parser.add_argument("--workdir", default="assets/tools_model")
  parser.add_argument("--samples", type=int, default=512)
  parser.add_argument("--fills", default=f"1.0,{CALIBRATED_FILL:.4f}")
  parser.add_argument("--boxes", default="ppd,true", help="ppd (the network's), true")
  parser.add_argument("--objects", type=int, default=0, help="0: every tool")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--out", required=True)
  args = parser.parse_args()
  fills = [float(f) for f in args.fills.split(",")]
  if not all(0 < f <= 2 for f in fills):
    parser.error(f"--fills must be in (0, 2], got {fills}")
  batch, ds = load_all(args.data)
  n = len(batch["voxels"]) if not args.objects else min(args.objects, len(batch["voxels"]))
  batch = jax.tree.map(lambda x: x[:n], batch)
  dec = decode(args.workdir, batch)
  slot = baselines.true_slots(batch["primitives"])
  valid = slot >= 0
  keys = jax.random.split(jax.random.key(args.seed), n)
  rec = {}  # (boxes, fill) -> {"dist": (n, S), "mae": (n, S), "slots": (n, S, K)}
  chosen = args.boxes.split(",")
  if not set(chosen) <= {"ppd", "true"}:
    parser.error(f"--boxes: ppd and/or true, got {chosen}")
  for boxes in chosen:
    prims = dec[boxes]
    cand = [np.asarray(sampling.candidate_slots(jnp.asarray(dec["logits"][i]),
                                                jnp.asarray(prims.valid[i]), args.samples,
                                                keys[i])[0]) for i in range(n)]
    for fill in fills:
      d, m = zip(*[score(jax.tree.map(lambda x: x[i], prims), cand[i], fill,
                         batch["trajectories"][i], ds.pushes)
                   for i in tqdm(range(n), desc=f"{boxes} boxes, fill {fill:.3f}")])
      rec[boxes, fill] = {"dist": np.stack(d), "mae": np.stack(m), "slots": np.stack(cand),
                          "logp": np.stack([np.asarray(sampling.log_prior(
                              jnp.asarray(dec["logits"][i]), jnp.asarray(cand[i]),
                              jnp.asarray(prims.valid[i]))) for i in range(n)])}
  table = {}
  for (boxes, fill), r in rec.items():
    pvalid = np.asarray(dec[boxes].valid)
    scores = rows.sample_scores(dec["logits"], r["slots"], r["dist"], pvalid)
    counts = rows.row_counts(scores, slot, valid)
    mae = r["mae"][np.arange(n), np.argmin(r["dist"], -1)]
    row = {**np_metrics(counts, np.arange(n)), "mae": float(mae.mean()),
           "ci95": intervals(counts, mae), "tau_sweep": {}}
    for tau in PRIOR_WEIGHTS:  # +Sample's τ on these tools: where to choose it
      obj = sampling.selection_objective(r["dist"], r["logp"], tau)
      c = rows.row_counts(rows.sample_scores(dec["logits"], r["slots"], obj, pvalid), slot,
                          valid)
      row["tau_sweep"][str(tau)] = {**np_metrics(c, np.arange(n)), "mae": float(
          r["mae"][np.arange(n), np.argmin(obj, -1)].mean())}
    table.setdefault(boxes, {})[f"{fill:.4f}"] = row
  plain = {"ppd": rows.row_counts(dec["logits"], slot, valid)}  # the network alone
  table["network alone"] = {k: np_metrics(v, np.arange(n)) for k, v in plain.items()}
  os.makedirs(args.out, exist_ok=True)
  with open(os.path.join(args.data, "manifest.json")) as f:
    made = json.load(f)  # the dataset's seed and size, for the command that made it
  command = "python experiments/tool_fill_study.py " + " ".join(sys.argv[1:])
  with open(os.path.join(args.out, "results.json"), "w") as f:
    json.dump({"command": command, "tools": n, "samples": args.samples, "fills": fills,
               "engine": "mujoco (C)", "table": table}, f, indent=1)
  lines = ["# +Sample on tools with the boxes' fill", "", f"`{command}`", "",
           f"{n} tools of `{args.data}` (a seed the tools model never saw; made by `python "
           f"-m ppdjax.generate --config=ppdjax/configs/tools.py --config.seed={made['seed']} "
           f"--config.data.num_tools={made['tools']} --out={args.data}`), {args.samples} "
           "network samples each, simulated with MuJoCo C at fill × their densities; "
           "+Sample picks the closest trajectory (τ = 0). 95 % intervals in brackets.", "",
           "| boxes | fill | top-1 | top-5 | top-10 | RMSE (slots) | MAE (mm) |",
           "|---|--:|--:|--:|--:|--:|--:|"]
  ci = lambda r, k: f"{r[k]:.1f} [{r['ci95'][k][0]:.1f}, {r['ci95'][k][1]:.1f}]"
  for boxes in chosen:
    for fill, r in table[boxes].items():
      lines.append(f"| {'network' if boxes == 'ppd' else 'true'} | {fill} | {ci(r, 'top1')} | "
                   f"{r['top5']:.1f} | {r['top10']:.1f} | {ci(r, 'rmse')} | {ci(r, 'mae')} |")
  lines += ["", "+Sample's τ (distance − τ · log prior) on these tools: top-1 / RMSE / MAE",
            "", "| boxes | fill | " + " | ".join(f"τ = {t}" for t in PRIOR_WEIGHTS) + " |",
            "|---|--:|" + "--:|" * len(PRIOR_WEIGHTS)]
  for boxes in chosen:
    for fill, r in table[boxes].items():
      lines.append(f"| {'network' if boxes == 'ppd' else 'true'} | {fill} | " + " | ".join(
          "{top1:.1f} / {rmse:.1f} / {mae:.1f}".format(**r["tau_sweep"][str(t)])
          for t in PRIOR_WEIGHTS) + " |")
  p = table["network alone"]["ppd"]
  lines += ["", f"The network alone (arg-max, no sampling): top-1 {p['top1']:.1f}, top-5 "
            f"{p['top5']:.1f}, top-10 {p['top10']:.1f}, RMSE {p['rmse']:.1f}.", ""]
  with open(os.path.join(args.out, "README.md"), "w") as f:
    f.write("\n".join(lines))
  print("\n".join(lines))


if __name__ == "__main__":
  main()
