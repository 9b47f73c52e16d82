"""The rows of one model's evaluation: how each ranks density slots, and its per-object records.

`evaluator.Evaluator` simulates every candidate of every group of boxes (`groups`) once
per batch; `batch_records` turns one batch's candidates into the records of Table 2's rows (PPD,
+Sample, +Sample+Refine, the +Fit, +Fit(depth) and true-box rows, the baselines), Table
4's prefixes, the τ sweep and the refinement statistics, which `tables.summarize` reduces
(with bootstrap intervals) to the tables.
"""

from __future__ import annotations

import numpy as np

from ppdjax.conventions import NUM_DENSITY_SLOTS, SLOT_DENSITY
from ppdjax.infer import sampling
from ppdjax.infer.posterior import log_weights
from ppdjax.report.tables import (BASELINES, FIT_ROWS, POSTERIOR_TEMPERATURES, PRIOR_WEIGHTS,
                                 SCREENS, SELECTION_HORIZONS, check_horizon)


SAMPLED_ABOVE = 1e9  # slots no sample has rank below every sampled one (objectives >= 0)


def log_softmax(logits):
  """Log-softmax over the last axis in float64, on the host."""
  lsm = np.asarray(logits, np.float64)
  lsm = lsm - lsm.max(-1, keepdims=True)
  return lsm - np.log(np.exp(lsm).sum(-1, keepdims=True))


def sample_scores(logits, slots, objective, valid):
  """(B, K, 100) +Sample ranking: slots a sample has, by that sample's best objective first.

  Slots no sample has follow in the network's order; boxes the network did not emit keep
  the network's scores.
  """
  b, s, k = slots.shape
  best = np.full((b, k, NUM_DENSITY_SLOTS), np.inf)
  bi, _, ki = np.meshgrid(np.arange(b), np.arange(s), np.arange(k), indexing="ij")
  np.minimum.at(best, (bi, ki, slots), np.broadcast_to(objective[:, :, None], slots.shape))
  lsm = log_softmax(logits)
  # float64 throughout: objectives differ by micrometres of trajectory distance (τ = 0), so
  # an offset such as 1e6 − objective in float32 (steps of 0.06) would tie every candidate
  out = np.where(np.isfinite(best), -np.where(np.isfinite(best), best, 0.0),
                 lsm - SAMPLED_ABOVE)
  return np.where(valid[..., None], out, logits)


def posterior_weights(distance, logp, temperature):
  """(B, S) log weights of the candidates under the posterior p(slots) · exp(−distance / T)
  over the sampled set (`infer.posterior.log_weights`, decompose's posterior), T in metres
  of trajectory distance; a string "rel:α" makes T = α × each object's least distance
  (noise that grows with the misfit). Shifted so that each object's best is 0."""
  relative = isinstance(temperature, str)
  scale = float(temperature.split(":")[1]) if relative else float(temperature)
  w = log_weights(np.asarray(distance, np.float64), np.asarray(logp, np.float64), scale,
                  relative=relative)
  return w - w.max(-1, keepdims=True)


def posterior_scores(logits, slots, log_weight, valid):
  """(B, K, 100) ranking by each box's posterior marginal: log Σ of the weights of the
  candidates that give the box that slot (a log-sum-exp per box and slot). Slots no
  candidate has follow in the network's order, as in `sample_scores`."""
  b, s, k = slots.shape
  flat = ((np.arange(b)[:, None, None] * k + np.arange(k)) * NUM_DENSITY_SLOTS
          + slots).ravel()
  w = np.broadcast_to(log_weight[:, :, None], slots.shape).ravel()
  top = np.full(b * k * NUM_DENSITY_SLOTS, -np.inf)
  np.maximum.at(top, flat, w)
  mass = np.bincount(flat, np.exp(w - top[flat]), minlength=top.size)
  sampled = np.isfinite(top)
  score = np.where(sampled, top + np.log(np.where(sampled, mass, 1.0)), 0.0)
  lsm = log_softmax(logits)
  out = np.where(sampled.reshape(b, k, -1), score.reshape(b, k, -1), lsm - SAMPLED_ABOVE)
  return np.where(valid[..., None], out, logits)


def posterior_records(row, logits, slots, distance, logp, mae, pvalid, slot, valid) -> dict:
  """+Sample's candidates read by each box's posterior marginal for every temperature of
  POSTERIOR_TEMPERATURES (free: the candidates are simulated once), keyed ("posterior",
  row, T, name); "mae" is that of the candidate of most posterior weight."""
  out = {}
  rows = np.arange(len(slot))
  for t in POSTERIOR_TEMPERATURES:
    w = posterior_weights(distance, logp, t)
    counts = row_counts(posterior_scores(logits, slots, w, pvalid), slot, valid)
    counts["mae"] = mae[rows, np.argmax(w, -1)]
    out.update({("posterior", row, t, k): v for k, v in counts.items()})
  return out


def refine_scores(logits, density, valid):
  """(B, K, 100) +Refine ranking: slots by distance to the refined (continuous) slot."""
  cont = density / SLOT_DENSITY - 1.0
  out = -np.abs(cont[..., None] - np.arange(NUM_DENSITY_SLOTS))
  return np.where(valid[..., None], out, logits)


def row_counts(scores, slot, valid, ks=(1, 5, 10)):
  """`metrics.density_counts` in NumPy (the same counts, tested): the records are made on
  the host, where a sweep's hundreds of small calls would each cost a round trip to an
  accelerator."""
  scores = np.asarray(scores, np.float64)  # never float32: see `sample_scores`
  truth = np.maximum(slot, 0)
  own = np.take_along_axis(scores, truth[..., None], -1)
  earlier = np.arange(scores.shape[-1]) < truth[..., None]
  rank = np.sum((scores > own) | ((scores == own) & earlier), -1)
  out = {f"top{k}": np.sum((rank < k) & valid, -1) for k in ks}
  err = np.argmax(scores, -1) - truth
  out["sq_err"] = np.sum(np.where(valid, err * err, 0), -1)
  out["count"] = np.sum(valid, -1)
  return out


def oracle_pick(row, logits, slots, slot, valid, pvalid) -> dict:
  """+Sample's ceiling on these candidates, keyed ("oracle_pick", row, name): the sample
  whose slots are closest to the truth (least squared slot error over the true boxes)
  picked by an oracle instead of by trajectory distance, and ("coverage", row) per box:
  whether any sample holds the true slot. What +Sample loses to its selection rule is the
  gap to the first; what it loses to the proposals, the first's gap to 100 %."""
  truth = np.maximum(slot, 0)[:, None, :]
  err = np.where(valid[:, None, :], (slots - truth).astype(np.float64) ** 2, 0.0).sum(-1)
  out = {("oracle_pick", row, k): v
         for k, v in row_counts(sample_scores(logits, slots, err, pvalid), slot, valid).items()}
  out[("coverage", row)] = np.any(slots == truth, axis=1) & valid
  return out


def screen_records(row, hdist, objective, mae, logits, slots, slot, valid, pvalid) -> dict:
  """Screened selection (`sampling.select_densities(screen_steps=)`) replayed on a +Sample
  row's exhaustively simulated candidates, for each (steps, keep) of SCREENS: the `keep`
  candidates closest over the first `steps` steps (hdist (B, S, H)), the best of them by
  `objective` (B, S). Keyed ("screen", row, steps, keep, name): "same" whether that is the
  exhaustive pick, "mae" its trajectory MAE and `row_counts` of its slots."""
  b, s = objective.shape
  rows = np.arange(b)
  exhaustive = np.argmin(objective, -1)
  out = {}
  for steps, keep in SCREENS:
    if keep >= s:
      continue
    prefix = hdist[..., SELECTION_HORIZONS.index(steps)]
    survivors = np.argsort(prefix, -1, kind="stable")[:, :keep]
    pick = survivors[rows, np.argmin(np.take_along_axis(objective, survivors, -1), -1)]
    counts = row_counts(sample_scores(logits, slots[rows, pick][:, None], np.zeros((b, 1)),
                                      pvalid), slot, valid)
    counts.update(mae=mae[rows, pick], same=pick == exhaustive)
    out.update({("screen", row, steps, keep, k): v for k, v in counts.items()})
  return out


def screen_mask(hdist, steps: int, keep: int):
  """(B, S) the candidates a screen keeps (`sampling.select_densities(screen_steps=)`,
  replayed on exhaustively simulated candidates): the `keep` closest over the first
  `steps` steps of hdist (B, S, H); all of them where `steps` is 0 or keep >= S."""
  b, s = hdist.shape[:2]
  if not steps or keep >= s:
    return np.ones((b, s), bool)
  prefix = hdist[..., SELECTION_HORIZONS.index(steps)]
  survivors = np.argsort(prefix, -1, kind="stable")[:, :keep]
  out = np.zeros((b, s), bool)
  np.put_along_axis(out, survivors, True, -1)
  return out


def _sweep(row, logits, slots, objective, mae, pvalid, slot, valid, selection_index,
           horizons: bool) -> dict:
  """A +Sample row's records for every τ in PRIOR_WEIGHTS (free: the candidates are
  simulated once), keyed ("sweep", row, τ, name), at the selection horizon; with
  `horizons`, for every horizon of SELECTION_HORIZONS too, keyed ("hsweep", row, horizon,
  τ, name) (0.4 s more per batch of 64 on a CPU core, hence optional)."""
  out = {}
  for hi, h in enumerate(SELECTION_HORIZONS):
    if not horizons and hi != selection_index:
      continue
    for tau in PRIOR_WEIGHTS:
      obj = objective(tau, hi)
      pick = np.argmin(obj, -1)
      counts = row_counts(sample_scores(logits, slots, obj, pvalid), slot, valid)
      counts["mae"] = mae[np.arange(len(pick)), pick]
      if horizons:
        out.update({("hsweep", row, h, tau, k): v for k, v in counts.items()})
      if hi == selection_index:
        out.update({("sweep", row, tau, k): v for k, v in counts.items()})
  return out


def batch_records(out: dict, slot, valid, base, *, samples: int, prior_weight: float,
                   prefixes, with_baselines: bool, refine: bool, layout: dict,
                   network_prior_weight: float | None = None,
                   selection_horizon: int = 0, horizon_sweep: bool = False,
                   table4: bool = True, studies: bool = False, headline: str = "ppd",
                   screen: tuple[int, int] = (0, 0)) -> dict:
  """Per-object records of one batch, keyed by (kind, row, name); `evaluation.evaluate`
  concatenates them and `tables.summarize` turns them into the tables. +Sample selects by
  the distance over the first `selection_horizon` steps (0: all; one of
  SELECTION_HORIZONS), out["hdist"] (B, C, H) holding each candidate's; Table 4's best of
  N and refinement's start use the whole trajectory (out["dist"]). `horizon_sweep` adds
  the τ sweep at every horizon (`_sweep`). `table4`: the batch simulated Table 4's
  sampling baselines (with the baselines on): then, and only then, every row's best of N
  is recorded, so that Table 4 compares its rows on the same objects. `headline`: the
  group whose +Sample row is `decompose`'s (`Evaluator.refine_group`); its selection
  keeps only the candidates `screen` (steps, keep) keeps, as `decompose` does. +Sample
  on the network's own boxes selects with `network_prior_weight` (None: `prior_weight`),
  on fitted ones with `prior_weight` (`SelectConfig.tau`).
  `studies`: also the sweeps (τ, temperatures, screens, oracle picks), free in rollouts
  but not in host time."""
  check_horizon("selection_horizon", selection_horizon)
  hi = SELECTION_HORIZONS.index(selection_horizon)
  keep = len(slot)
  rows = np.arange(keep)
  pvalid = np.asarray(out["pred"].valid)
  logits = out["logits"].astype(np.float64)
  slots = out["slots"]
  hdist, omae = out["hdist"][:, layout["ppd"]], out["mae"][:, layout["ppd"]]
  dist = out["dist"][:, layout["ppd"]]
  objective = lambda tau, h=hi, keep=screen_mask(hdist, *screen) if headline == "ppd" else 1: (
      np.where(keep, sampling.selection_objective(hdist[..., h], out["logp"], tau), np.inf))
  rec = {("blocks",): valid.sum(-1), ("true_slot",): slot, ("true_valid",): valid}
  rec.update({("shape", k): np.asarray(v) for k, v in out["shape"].items()})
  rec.update({("faces", g): np.asarray(v) for g, v in out["faces"].items()})  # (B, K, 6) m
  tau = prior_weight if network_prior_weight is None else network_prior_weight
  best = np.argmin(objective(tau), -1)
  pick = (slots[rows, best], omae[rows, best])  # the +Sample answer of `headline`
  scores = {"PPD": logits, "PPD+Sample": sample_scores(logits, slots, objective(tau), pvalid)}
  mae = {"PPD": omae[:, 0], "PPD+Sample": omae[rows, best]}
  if studies:
    rec.update(_sweep("PPD+Sample", logits, slots, objective, omae, pvalid, slot, valid, hi,
                       horizon_sweep))
    rec.update(oracle_pick("PPD+Sample", logits, slots, slot, valid, pvalid))
    rec.update(posterior_records("PPD+Sample", logits, slots, hdist[..., hi], out["logp"],
                                 omae, pvalid, slot, valid))
    rec.update(screen_records("PPD+Sample", hdist, objective(tau), omae, logits,
                              slots, slot, valid, pvalid))
  table4 = table4 or not with_baselines  # without the baselines: the network's rows
  if table4:
    for p in prefixes:
      rec[("prefix", "PPD", p)] = omae[rows, np.argmin(dist[:, :p], -1)]
  if with_baselines:
    base_mae = out["mae"][:, layout["baselines"]]
    for j, name in enumerate(BASELINES):
      scores[name] = base[:, j]
      mae[name] = base_mae[:, j]
    for group, name in (("uniform", "Sample Phys."), ("shapes", "Sample Phys.+Shape")):
      if not table4:
        break
      d, e = out["dist"][:, layout[group]], out["mae"][:, layout[group]]
      for p in prefixes:
        rec[("prefix", name, p)] = e[rows, np.argmin(d[:, :p], -1)]
  sample_row = "PPD+Sample"
  for group in [g for g in FIT_ROWS if g in layout]:  # the same rows on fitted boxes
    name = FIT_ROWS[group]
    rec.update({("shape_" + group, k): np.asarray(v) for k, v in out["shape_" + group].items()})
    fvalid = np.asarray(out["fitted"][group].valid)
    glogits = out["group_logits"][group].astype(np.float64)
    fd, fm = out["dist"][:, layout[group]], out["mae"][:, layout[group]]
    fhd = out["hdist"][:, layout[group]]
    keep = screen_mask(fhd, *screen) if group == headline else 1
    f_objective = lambda tau, h=hi, fhd=fhd, g=group, keep=keep: np.where(
        keep, sampling.selection_objective(fhd[..., h], out["fit_logp"][g], tau), np.inf)
    f_obj = f_objective(prior_weight)
    f_best = np.argmin(f_obj, -1)
    if group == headline:
      pick = (out["fit_slots"][group][rows, f_best], fm[rows, f_best])
    scores[name] = glogits
    mae[name] = fm[:, 0]
    scores[name + "+Sample"] = sample_scores(glogits, out["fit_slots"][group], f_obj, fvalid)
    mae[name + "+Sample"] = fm[rows, f_best]
    if studies:
      rec.update(_sweep(name + "+Sample", glogits, out["fit_slots"][group], f_objective, fm,
                        fvalid, slot, valid, hi, horizon_sweep))
      rec.update(oracle_pick(name + "+Sample", glogits, out["fit_slots"][group], slot, valid,
                             fvalid))
      rec.update(posterior_records(name + "+Sample", glogits, out["fit_slots"][group],
                                   fhd[..., hi], out["fit_logp"][group], fm, fvalid, slot,
                                   valid))
      rec.update(screen_records(name + "+Sample", fhd, f_obj, fm, glogits,
                                out["fit_slots"][group], slot, valid, fvalid))
    if group != "true":  # +Refine and +Joint start from the most precise fit
      sample_row, pvalid = name + "+Sample", fvalid
    for p in prefixes if table4 else ():
      rec[("prefix", name, p)] = fm[rows, np.argmin(fd[:, :p], -1)]
  if "est_logits" in out:  # the estimator alone, on the boxes it read
    scores["Estimator"] = out["est_logits"].astype(np.float64)  # no MAE: nothing simulated
  if "joint" in out:  # faces and densities together, from the same start as +Refine
    j = out["joint"]
    scores[sample_row + "+Joint"] = refine_scores(logits, j["density"], pvalid)
    mae[sample_row + "+Joint"] = j["mae"]
    rec[("faces", "joint")] = np.asarray(j["faces"])
  if refine:  # `decompose`'s answer: refined where it came closer, else +Sample's
    r = out["refine"]
    closer = np.asarray(r["closer"], bool)
    density = np.where(closer[:, None], r["density"], SLOT_DENSITY * (pick[0] + 1.0))
    scores[sample_row + "+Refine"] = refine_scores(logits, density, pvalid)
    mae[sample_row + "+Refine"] = np.where(closer, r["mae"], pick[1])
    rec.update({("refine", k): r[k] for k in ("cost_start", "cost", "dist", "sample_dist")})
  if "refine_true" in out:  # the oracle column, refined alike
    scores[FIT_ROWS["true"] + "+Sample+Refine"] = refine_scores(
        logits, out["refine_true"]["density"], np.asarray(out["fitted"]["true"].valid))
    mae[FIT_ROWS["true"] + "+Sample+Refine"] = out["refine_true"]["mae"]
  for name, sc in scores.items():
    rec.update({("counts", name, k): v for k, v in row_counts(sc, slot, valid).items()})
    rec[("guess", name)] = np.argmax(sc, -1)
    if name in mae:
      rec[("mae", name)] = mae[name]
  return rec
