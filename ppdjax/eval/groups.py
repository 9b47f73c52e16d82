"""The groups of boxes an evaluation samples densities on: which there are, where their
candidates sit along an object's candidate axis, and how each group's boxes are made.

Groups: "ppd" (the network's boxes), "fit" (fitted to the voxels, `fit.fit_boxes`, and
with `image_fit` to the image's edges, `image_fit`),
"fit_depth" (then to the depth image, `depth_fit`), "..._est" (the most precise fit,
scored with the density estimator too) and "true" (the oracle column: the true boxes).
`evaluator.Evaluator` decodes them once per batch (`decode_groups`) and simulates every
group's candidates in one batched call.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import nnx

from ppdjax import metrics
from ppdjax.conventions import NUM_DENSITY_SLOTS
from ppdjax.infer.config import DecomposeConfig, FitConfig
from ppdjax.infer.decompose import fit_stage
from ppdjax.report.tables import BASELINES, FIT_ROWS
from ppdjax.nn.estimator import combine_logits
from ppdjax.primitives import bottom_to_top


def fit_groups(fit: FitConfig, estimator: bool = False) -> tuple[str, ...]:
  """The fitted-box groups of an evaluation of `decompose` with this fit: "fit" (voxels,
  and the image where the fit reads it) or "fit_depth" (the fit reads the depth); with an
  estimator, the same boxes again, scored with it ("..._est", `decompose`'s answer)."""
  if not fit.enabled:
    if estimator:
      raise ValueError("the estimator reads fitted boxes: it needs fit.enabled")
    return ()
  group = "fit_depth" if fit.depth else "fit"
  return (group,) + ((group + "_est",) if estimator else ())


def headline_row(decompose: DecomposeConfig) -> str:
  """The Table 2 row an evaluation with these settings names `decompose`'s answer: the
  +Sample (+Refine) row of the group its boxes are (`fit_groups`' last)."""
  fits = fit_groups(decompose.fit, bool(decompose.estimator.path))
  name = FIT_ROWS.get(fits[-1] if fits else "ppd", "PPD") + "+Sample"
  return name + "+Refine" if decompose.refine.enabled else name


def candidate_layout(samples: int, fits: tuple[str, ...], with_baselines: bool) -> dict:
  """Where each group of candidates sits along an object's candidate axis: name -> slice.

  "ppd": the network's samples on its boxes; "fit" / "fit_depth" (`fits`): the network's
  samples on the fitted boxes ("..._est": the combined scores' samples on them; "true":
  on the true boxes);
  "baselines": Table 2's three guesses;
  "uniform" / "shapes": Table 4's sampling baselines, last (`evaluator.Evaluator`
  simulates them with the others when Table 4 covers every batch, otherwise in a call of
  their own on the batches it covers).
  """
  sizes = [("ppd", samples)] + [(g, samples) for g in fits]
  if with_baselines:
    sizes += [("baselines", len(BASELINES)), ("uniform", samples), ("shapes", samples)]
  out, start = {}, 0
  for name, n in sizes:
    out[name] = slice(start, start + n)
    start += n
  return out


def decode_groups(graphdef, state, obs, true, est_state=None, *, groups, camera, fit,
                  est_graphdef=None, est_weight=1.0, true_shapes=False):
  """The network's boxes and slot logits, and per fit group the fitted boxes
  (`decompose.fit_stage` with the `fit` settings, as `decompose` fits them; the k-th
  logits go to the k-th fitted box from the bottom) and their logits
  ("group_logits": the network's, or with the estimator combined with its); shape counts
  of each ("shape", "shape_fit", "shape_fit_depth"). With `true_shapes`, the true boxes
  too, as group "true" with the network's logits."""
  model = nnx.merge(graphdef, state)
  pred, raw = model.decode(obs)
  logits = raw.density_logits[:, :pred.num_slots, :NUM_DENSITY_SLOTS]
  out = {"pred": pred, "logits": logits, "shape": metrics.shape_counts(pred, true),
         "fitted": {}, "faces": {"ppd": metrics.face_errors(bottom_to_top(pred), true)},
         "group_logits": {g: logits for g in groups}}
  if groups:
    out["fitted"][groups[0]] = fit_stage(obs, pred, fit, camera)
  for g, boxes in list(out["fitted"].items()):
    out["fitted"][g] = boxes.replace(density=pred.density)
    out["shape_" + g] = metrics.shape_counts(boxes, true)
    out["faces"][g] = metrics.face_errors(bottom_to_top(boxes), true)
  if est_graphdef is not None:  # the estimator reads the most precise fitted boxes
    g, base = groups[-1], groups[-1].removesuffix("_est")
    boxes = out["fitted"][base]
    est = nnx.merge(est_graphdef, est_state)(boxes, obs["trajectories"].astype(jnp.float32))
    out["fitted"][g], out["shape_" + g] = boxes, out["shape_" + base]
    out["est_logits"] = est
    out["group_logits"][g] = combine_logits(logits, est, est_weight)
  if true_shapes:  # the oracle column: the network's k-th logits on the k-th true box
    out["fitted"]["true"] = true.replace(density=pred.density)
    out["shape_true"], out["group_logits"]["true"] = metrics.shape_counts(true, true), logits
  return out
