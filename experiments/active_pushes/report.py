"""The closed loop's report: accuracy, interval width and coverage by policy and pushes made,
paired intervals over towers, the choices made on validation (the posterior's temperature,
the refinement's prior weight, the choosing policy for "active"), and the plot.

  python experiments/active_pushes/run.py report --val_records=VAL.npz --records=TEST.npz \
      --out=experiments/results/posterior.json
"""

from __future__ import annotations

import json
import os

import numpy as np

from ppdjax import metrics
from ppdjax.report.provenance import read_provenance, write_provenance

POLICIES = ("fixed", "random", "active")
REFINED = "_refined"  # a policy's answers refined after each push (refine_loop)
DESIGN = "design"  # + horizon: pushes chosen on the refined answer (design.design_loop)
MAX_PUSHES = 4


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


def policies_of(rec) -> tuple[str, ...]:
  """The policies a record holds: POLICIES, then the design loops it ran."""
  horizons = rec["design_horizons"] if "design_horizons" in rec else []
  return POLICIES + tuple(f"{DESIGN}{int(h)}" for h in horizons)


def policy_rows(curves: dict, towers: np.ndarray) -> dict:
  """The results file's rows of one way to decompose: fixed four, random four, each
  choosing policy's two and four (active: the gain over the candidates; designNN: the
  refined answer's Laplace posterior), their paired differences, and every policy by
  pushes made."""
  c = curves
  rows = {"fixed4": summary(c["fixed"][3], towers), "random4": summary(c["random"][3], towers)}
  pairs = {}
  for p in [p for p in c if p not in ("fixed", "random")]:
    rows.update({f"{p}2": summary(c[p][1], towers), f"{p}4": summary(c[p][3], towers)})
    pairs.update({f"{p}2_minus_fixed4": paired(c["fixed"][3], c[p][1], towers),
                  f"{p}2_minus_fixed2": paired(c["fixed"][1], c[p][1], towers),
                  f"{p}4_minus_fixed4": paired(c["fixed"][3], c[p][3], towers),
                  f"{p}4_minus_random4": paired(c["random"][3], c[p][3], towers)})
  return {**rows, "paired": pairs, "by_pushes": {p: [summary(x, towers) for x in c[p]]
                                                 for p in c}}


def as_active(rows: dict, policy: str) -> dict:
  """`rows` (`policy_rows`) with `policy`'s rows under the issue's names (active2,
  active4, their paired differences) and the others' dropped."""
  out = {"fixed4": rows["fixed4"], "random4": rows["random4"],
         "active2": rows[f"{policy}2"], "active4": rows[f"{policy}4"],
         "paired": {k.replace(policy, "active", 1): v for k, v in rows["paired"].items()
                    if k.split("_minus_")[0] in (f"{policy}2", f"{policy}4")},
         "policy": policy}
  return out


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
  policies = policies_of(rec)
  curves = {p: [scores(rec, p, k, chosen) for k in range(1, MAX_PUSHES + 1)]
            for p in policies}
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
    w, w_val = int(at[0]), int(np.argmin(val_rmse))
    curves_at = lambda clip: {p: [scores(rec, p + REFINED, k, chosen, w, clip)  # noqa: E731
                                  for k in range(1, MAX_PUSHES + 1)] for p in policies}
    # the choosing policy of the refined loop: the lowest refined RMSE after four pushes on
    # validation, among the gain over the candidates and the design loops
    if policies_of(val) != policies:
      raise ValueError(f"the validation records hold the policies {policies_of(val)}, the "
                       f"test records {policies}: record both alike")
    val_rmse4 = {}
    for p in policies[2:]:
      c = scores(val, p + REFINED, MAX_PUSHES, chosen, w_val)
      val_rmse4[p] = float(np.sqrt(c["sq"][c["same"]].sum() / c["boxes"][c["same"]].sum()))
    refined = {**policy_rows(curves_at(False), towers),
               "chosen_policy": min(val_rmse4, key=val_rmse4.get),
               "validation_rmse4_by_policy": val_rmse4,
               "kept_share": {p: [float(by_weight(rec, f"{p}{REFINED}_closer")[towers, w,
                                                                              k].mean())
                                  for k in range(MAX_PUSHES)] for p in policies},
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
                                       minlength=64).tolist() for p in policies[1:]},
      "refined": refined,
      "command": ("python experiments/active_pushes/run.py report "
                  f"--val_records={val_records} --records={records}")})
  result = {}
  if os.path.exists(out):
    with open(out) as f:
      result = json.load(f)
  result.setdefault("active_by_setting", {})[setting] = active_result
  by_setting = result["active_by_setting"]
  plot({**active_result["by_pushes"],
        **{p + REFINED: rows for p, rows in (refined or {}).get("by_pushes", {}).items()}},
       f"{os.path.splitext(out)[0]}_active_{setting}.png")
  made_by = [result.get("command")] + [r["command"] for r in by_setting.values()]
  write_provenance(out, command="; ".join(c for c in made_by if c))  # calibration's, each loop's
  active_result["commit"] = read_provenance(out).get("commit")
  # the depth setting's refined loop (the depth preset refines) with the choosing policy
  # validation chose; records without refinement: the +Sample loop's gain over candidates
  head = by_setting.get("depth", by_setting.get("paper_inputs"))
  about = {k: head.get(k) for k in ("setting", "towers", "boxes", "scale", "commit")}
  if head.get("refined"):
    result["active"] = {**as_active(head["refined"],
                                    head["refined"].get("chosen_policy", "active")),
                        "loop": "refined", "prior_weight": head["refined"]["prior_weight"],
                        **about}
  else:
    result["active"] = {**as_active(head, "active"), "loop": "sample", **about}
  with open(out, "w") as f:
    json.dump(result, f, indent=1)
  print(json.dumps({k: v for k, v in active_result.items() if k != "by_pushes"}, indent=1)[:3000])


def plot(by_pushes: dict, path: str) -> None:
  """Top-1, RMSE and interval width against the number of pushes made, per policy."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  fig, axes = plt.subplots(1, 3, figsize=(13, 3.4))
  x = np.arange(1, MAX_PUSHES + 1)
  for ax, key, label in zip(axes, ("top1", "rmse", "width"),
                            ("density top-1 (%)", "density RMSE (slots)",
                             "90 % interval width (slots)")):
    names = list(dict.fromkeys(p.removesuffix(REFINED) for p in by_pushes))
    for i, (p, rows) in enumerate(by_pushes.items()):
      if key == "width" and p.endswith(REFINED):  # the candidates' intervals: the same
        continue
      y = [r[key] for r in rows]
      lo, hi = zip(*[r[f"{key}_ci95"] for r in rows])
      ax.errorbar(x + 0.05 * (i - 1), y, yerr=[np.subtract(y, lo), np.subtract(hi, y)],
                  marker="o", capsize=3, label=p, color=f"C{names.index(p.removesuffix(REFINED))}",
                  linestyle="--" if p.endswith(REFINED) else "-")
    ax.set(xlabel="pushes made", ylabel=label, xticks=x)
  fig.legend(*axes[0].get_legend_handles_labels(), loc="center right", fontsize=8)
  fig.tight_layout(rect=(0, 0, 0.86, 1))  # the legend to the right: ten series
  fig.savefig(path, dpi=110)
