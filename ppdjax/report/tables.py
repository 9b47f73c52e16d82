"""The paper's published numbers (Tables 2, 4, 5, shape F1), the evaluation's row names, and
the reduction of its per-object records to tables (`summarize`); `markdown` lays them out."""

from __future__ import annotations


import numpy as np

from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.dataset.materials import ALL_MATERIAL_NAMES, MATERIAL_NAMES, MATERIALS

# Row and column names of one model's evaluation.
BASELINES = ("Frequent", "Nearest", "Oracle")
# Boxes fitted at test time (`groups.fit_groups`): group -> the prefix of its rows.
# "..._est": the same boxes scored with the density estimator too (groups.fit_groups).
# "true": the network's density scores on the true boxes (the oracle shape column, a bound
# on what better boxes can give; `evaluate(..., true_shapes=True)`).
FIT_ROWS = {"fit": "PPD+Fit", "fit_depth": "PPD+Fit(depth)", "fit_est": "PPD+Fit+Est",
            "fit_depth_est": "PPD+Fit(depth)+Est", "true": "PPD+True boxes"}
PPD_ROWS = ("PPD", "PPD+Sample", "PPD+Sample+Refine") + tuple(
    f + s for f in FIT_ROWS.values() for s in ("", "+Sample", "+Sample+Refine",
                                                 "+Sample+Joint")) + ("Estimator",)
PREFIXES = (1, 8, 64, 512)  # Table 4's sample counts
# τ swept for +Sample (m per nat); the estimator study chose 0.1, so the sweep goes past it
PRIOR_WEIGHTS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
# +Sample read by each box's posterior marginal (`rows.posterior_records`): temperatures T
# of the likelihood exp(−distance / T), in metres, or "rel:α" for α × the object's least
# distance
POSTERIOR_TEMPERATURES = (1e-4, 3e-4, 1e-3, 3e-3, "rel:0.03", "rel:0.1", "rel:0.3", "rel:1")
# +Sample's distance over the first h steps, swept beside τ (0: all steps, the paper's)
SELECTION_HORIZONS = (16, 32, 64, 128, 0)

# screened selection replayed on the exhaustive candidates (`rows.screen_records`): every
# candidate over the first `steps` steps (one of SELECTION_HORIZONS), the `keep` closest whole
SCREENS = ((16, 32), (16, 64), (32, 32), (32, 64), (32, 128), (64, 64), (64, 128))

# --- the paper's published numbers (block towers), the one copy every report reads -------

# Table 2: top-1, top-5, top-10 (%), RMSE (slots), trajectory MAE, by row name.
PAPER_TABLE2 = {
    "Frequent": (2.0, 9.7, 13.4, 25.4, 74.4), "Nearest": (1.9, 7.9, 12.4, 41.1, 91.0),
    "Oracle": (6.9, 35.7, 72.0, 18.5, 51.3),
    "PPD (no trajectory)": (7.2, 35.2, 69.5, 19.0, 51.7),
    "PPD (no image)": (7.1, 31.0, 50.8, 16.7, 36.4),
    "PPD (no voxels)": (15.9, 56.3, 82.4, 10.3, 29.9),
    "PPD (RGB-D)": (11.6, 50.5, 79.5, 12.8, 30.2),
    "PPD (full)": (16.1, 56.4, 82.5, 9.9, 21.0),
    "PPD (full)+Sample": (18.2, 59.7, 84.0, 8.8, 13.9)}
# One model's evaluation names its rows without the variant: PPD, PPD+Sample, baselines.
PAPER_TABLE2_ONE_MODEL = {
    **{k: PAPER_TABLE2[k] for k in ("Frequent", "Nearest", "Oracle")},
    "PPD": PAPER_TABLE2["PPD (full)"], "PPD+Sample": PAPER_TABLE2["PPD (full)+Sample"]}
# Table 4: trajectory MAE of the best of 1, 8, 64, 512 samples.
PAPER_TABLE4 = {"Sample Phys.+Shape": (142.2, 87.1, 70.8, 58.7),
                "Sample Phys.": (89.7, 60.1, 38.7, 22.7), "PPD": (21.0, 15.1, 13.9, 13.2)}
# Table 5: density RMSE (slots) for towers of 2, 3, 4, 5 blocks, and overall.
PAPER_TABLE5 = {"Texture": (18.2, 18.5, 18.8, 19.7, 19.1),
                "Physics": (3.6, 7.9, 15.8, 20.0, 14.7),
                "Texture + Physics": (2.3, 4.9, 7.8, 10.9, 8.0)}
PAPER_SHAPE_F1 = 97.5  # shape F1 (%) of the full model on block towers


def check_horizon(name: str, steps) -> None:
  """Raises ValueError unless `steps` is one of SELECTION_HORIZONS (the distances the
  evaluation computes); `name` is the setting's, for the message."""
  if steps not in SELECTION_HORIZONS:
    raise ValueError(f"{name} must be one of {SELECTION_HORIZONS} (0: all steps), got {steps}")


def model_switches(config) -> dict:
  """Which encoders a model uses (what its Table 2 row observes)."""
  return {k: bool(config.model[k]) for k in ("use_voxels", "use_image", "use_trajectory")}


def np_metrics(counts: dict, idx) -> dict:
  """top-k (%) and RMSE (slots) of the objects `idx` (NumPy; the bootstrap's inner loop)."""
  n = max(float(counts["count"][idx].sum()), 1.0)
  out = {k: 100.0 * float(v[idx].sum()) / n for k, v in counts.items() if k.startswith("top")}
  out["rmse"] = float(np.sqrt(counts["sq_err"][idx].sum() / n))
  return out


def intervals(counts: dict, mae, resamples: int = 1000, groups=None) -> dict:
  """95 % bootstrap intervals of a row's top-k, RMSE and MAE, over objects or, with
  `groups` (an id per object), over whole groups (`metrics.bootstrap_interval`)."""
  n = len(counts["count"])
  out = {}
  for k in [k for k in counts if k.startswith("top")] + ["rmse"]:
    out[k] = metrics.bootstrap_interval(lambda i, k=k: np_metrics(counts, i)[k], n,
                                        resamples=resamples, groups=groups)
  if mae is not None:
    out["mae"] = metrics.bootstrap_interval(lambda i: float(np.mean(mae[i])), n,
                                            resamples=resamples, groups=groups)
  return out


def by_blocks(counts: dict, blocks, groups=None) -> tuple[dict, dict]:
  """Table 5 of one row: density RMSE of the objects of each block count from 2 up, and
  its 95 % bootstrap interval (over `groups` if given), keyed by the count as a string."""
  present = [b for b in range(2, blocks.max() + 1) if np.any(blocks == b)]
  rmse = {str(b): metrics.summarize({k: v[blocks == b] for k, v in counts.items()})["rmse"]
          for b in present}
  ci95 = {}
  for b in present:
    sel = np.flatnonzero(blocks == b)
    ci95[str(b)] = metrics.bootstrap_interval(
        lambda i, sel=sel: np_metrics(counts, sel[i])["rmse"], len(sel),
        groups=None if groups is None else groups[sel])
  return rmse, ci95


def _f1(rec, kind, groups=None):
  c = [np.asarray(rec[(kind, k)]) for k in ("matched", "predicted", "true")]
  f1 = lambda i: metrics.f1_from_counts(c[0][i], c[1][i], c[2][i])
  exact = lambda i: 100.0 * float(np.mean(c[1][i] == c[2][i]))
  everyone = np.arange(len(c[0]))
  return {"f1": f1(everyone),
          "f1_ci95": metrics.bootstrap_interval(f1, len(everyone), groups=groups),
          "count_exact": exact(everyone),
          "count_exact_ci95": metrics.bootstrap_interval(exact, len(everyone), groups=groups)}


def face_summary(errors_BxKx6) -> dict:
  """Median, p90 and max (mm) of face errors over every face of every matched box, and
  the median per face direction (`metrics.FACE_NAMES`)."""
  e = 1e3 * np.asarray(errors_BxKx6, np.float64)
  flat = e[np.isfinite(e)]
  if flat.size == 0:
    return {"faces": 0}
  per = {n: float(np.nanmedian(e[..., i])) for i, n in enumerate(metrics.FACE_NAMES)}
  return {"faces": int(flat.size), "median": float(np.median(flat)),
          "p90": float(np.percentile(flat, 90)), "max": float(flat.max()), "median_by_face": per}


# what the intervals resample (summarize's keys) and what a geometry is (the evaluation's)
INTERVAL_KEYS = ("intervals_over", "geometries", "data_kind")


def by_material(slot, valid, material, guesses: dict) -> dict:
  """Per row, per material of the true box (`materials.ALL_MATERIAL_NAMES`): boxes, top-1
  (%) and RMSE (slots) of the row's arg-max guesses, and for metal, whose slots lie in two
  ranges (aluminium-like and steel-like), "range_confusions": the boxes guessed in the
  other range, as a percentage of every box."""
  names = np.asarray(ALL_MATERIAL_NAMES)
  out = {}
  metal = MATERIALS["metal"]
  for row, guess in guesses.items():
    out[row] = {}
    for m in np.unique(material[valid & (material >= 0)]):  # -1: a box of no material
      pick = valid & (material == m)
      err = guess[pick].astype(np.int64) - slot[pick]
      out[row][str(names[m])] = {"boxes": int(pick.sum()),
                                 "top1": 100.0 * float(np.mean(err == 0)),
                                 "rmse": float(np.sqrt(np.mean(err ** 2)))}
    # 0-based slots of metal's ranges: low (lo..hi) and high
    in_range = lambda s, r: (s >= r[0] - 1) & (s <= r[1] - 1)  # noqa: E731
    is_metal = valid & (material == MATERIAL_NAMES.index("metal"))
    crossed = is_metal & ((in_range(slot, metal[0]) & in_range(guess, metal[1]))
                          | (in_range(slot, metal[1]) & in_range(guess, metal[0])))
    out[row]["range_confusions"] = 100.0 * float(crossed.sum()) / max(int(valid.sum()), 1)
  return out


def summarize(switches: dict, rec: dict, geometries=None) -> dict:
  """Tables 2, 4, 5, F1, the τ sweep, refinement statistics and confusion matrices from
  the concatenated per-object records of `rows.batch_records`, with 95 % bootstrap
  intervals ("ci95") for Table 2's rows, Table 5 and F1. `geometries` (an id per object,
  the dataset's "tower_id"): the intervals resample whole towers or tools, whose density
  configurations share a shape; None: single objects (`metrics.bootstrap_interval`)."""
  group = lambda *prefix: {k[len(prefix)]: v for k, v in rec.items()
                           if k[:len(prefix)] == prefix and len(k) == len(prefix) + 1}
  nb = rec[("blocks",)]
  g = None if geometries is None else np.asarray(geometries)
  shape = _f1(rec, "shape", g)
  results = {"model": switches, "mae_units": "mm", "table2": {}, "table4": {}, "table5": {},
             "table5_ci95": {}, "f1": shape["f1"], "shape": shape,
             "intervals_over": "objects" if g is None else "geometries",
             "geometries": None if g is None else int(len(np.unique(g)))}
  for fit in FIT_ROWS:  # "shape_fit" / "f1_fit", "shape_fit_depth" / "f1_fit_depth"
    if ("shape_" + fit, "matched") in rec:
      results["shape_" + fit] = _f1(rec, "shape_" + fit, g)
      results["f1_" + fit] = results["shape_" + fit]["f1"]
  names = {k[1] for k in rec if k[0] == "counts"}
  for name in [r for r in BASELINES + PPD_ROWS if r in names]:
    counts = {k: np.asarray(v) for k, v in group("counts", name).items()}
    row = metrics.summarize(counts)
    mae = rec.get(("mae", name))  # None for a row that simulates nothing (Estimator)
    row["mae"] = None if mae is None else float(np.mean(mae))
    row["ci95"] = intervals(counts, None if mae is None else np.asarray(mae), groups=g)
    results["table2"][name] = row
    results["table5"][name], results["table5_ci95"][name] = by_blocks(counts, nb, g)
    results["table5"][name]["overall"] = row["rmse"]
  # face error (mm) of the network's ("ppd"), fitted ("fit") and depth-fitted boxes
  results["face_error_mm"] = {g[1]: face_summary(rec[g]) for g in rec if g[0] == "faces"}
  results["prior_sweeps"] = {}  # +Sample row -> τ -> metrics
  for row in sorted({k[1] for k in rec if k[0] == "sweep"}, key=PPD_ROWS.index):
    sweep = results["prior_sweeps"][row] = {}
    for tau in PRIOR_WEIGHTS:
      counts = group("sweep", row, tau)
      mae = counts.pop("mae")
      sweep[str(tau)] = {**metrics.summarize(counts), "mae": float(np.mean(mae))}
  results["prior_sweep"] = results["prior_sweeps"].get("PPD+Sample", {})  # as before
  results["selection_sweeps"] = {}  # +Sample row -> horizon -> τ -> metrics
  for row, h, tau in sorted({k[1:4] for k in rec if k[0] == "hsweep"},
                            key=lambda k: (PPD_ROWS.index(k[0]), k[1] or 10**9, k[2])):
    counts = group("hsweep", row, h, tau)
    mae = counts.pop("mae")
    results["selection_sweeps"].setdefault(row, {}).setdefault(str(h), {})[str(tau)] = {
        **metrics.summarize(counts), "mae": float(np.mean(mae))}
  results["posterior_sweeps"] = {}  # +Sample row -> T -> metrics, Table 5 by blocks
  for row in sorted({k[1] for k in rec if k[0] == "posterior"}, key=PPD_ROWS.index):
    for t in POSTERIOR_TEMPERATURES:
      counts = {k: np.asarray(v) for k, v in group("posterior", row, t).items()}
      mae = counts.pop("mae")
      table5, table5_ci95 = by_blocks(counts, nb, g)
      results["posterior_sweeps"].setdefault(row, {})[str(t)] = {
          **metrics.summarize(counts), "mae": float(np.mean(mae)), "table5": table5,
          "table5_ci95": table5_ci95}
  results["oracle_pick"] = {}  # +Sample row -> its ceiling on the same candidates
  for row in sorted({k[1] for k in rec if k[0] == "oracle_pick"}, key=PPD_ROWS.index):
    counts = group("oracle_pick", row)
    cover, valid = rec[("coverage", row)], rec[("true_valid",)]
    results["oracle_pick"][row] = {
        **metrics.summarize(counts), "ci95": intervals(counts, None, groups=g),
        "coverage": 100.0 * float(cover.sum()) / max(float(valid.sum()), 1.0)}
  results["screens"] = {}  # +Sample row -> "steps:keep" -> metrics and agreement
  for row, steps, keep in sorted({k[1:4] for k in rec if k[0] == "screen"},
                                 key=lambda k: (PPD_ROWS.index(k[0]), k[1], k[2])):
    counts = group("screen", row, steps, keep)
    mae, same = counts.pop("mae"), counts.pop("same")
    results["screens"].setdefault(row, {})[f"{steps}:{keep}"] = {
        **metrics.summarize(counts), "mae": float(np.mean(mae)),
        "same_pick": 100.0 * float(np.mean(same)),
        "same_pick_ci95": metrics.bootstrap_interval(
            lambda i, same=same: 100.0 * float(np.mean(same[i])), len(same), groups=g)}
  for k, v in rec.items():
    if k[0] == "prefix":
      results["table4"].setdefault(k[1], {})[str(k[2])] = float(np.mean(v))
  if ("refine", "cost") in rec:
    r = group("refine")
    d0, d1 = r["sample_dist"], r["dist"]
    results["refine_stats"] = {
        "improved_fraction": float(np.mean(d1 < d0 - 1e-9)),
        "median_distance_ratio": float(np.median(d1 / np.maximum(d0, 1e-12))),
        "mean_distance_sample_m": float(d0.mean()), "mean_distance_refined_m": float(d1.mean()),
        "mean_cost_start": float(r["cost_start"].mean()), "mean_cost": float(r["cost"].mean())}
  slot, valid = rec[("true_slot",)], rec[("true_valid",)]
  if ("true_material",) in rec:
    guesses = {name: rec[("guess", name)] for name in PPD_ROWS if ("guess", name) in rec}
    results["by_material"] = by_material(slot, valid, rec[("true_material",)], guesses)
    # the network's and +Sample's hits per object, in the evaluated order: what a breakdown
    # by a property of the objects (a tool's category) reads
    results["per_object"] = {
        name: {k: np.asarray(v).tolist() for k, v in group("counts", name).items()
               if k in ("top1", "sq_err", "count")}
        for name in ("PPD", "PPD+Sample") if name in names}
  results["confusion"] = {}
  for name in [r for r in PPD_ROWS if r in names]:
    matrix = np.zeros((NUM_DENSITY_SLOTS,) * 2, np.int64)
    np.add.at(matrix, (slot[valid], rec[("guess", name)][valid]), 1)
    results["confusion"][name] = matrix.tolist()
  return results
