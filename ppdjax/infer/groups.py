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
from ppdjax.infer.fit import fit_boxes, refine_fitted
from ppdjax.infer.tables import BASELINES
from ppdjax.nn.estimator import combine_logits
from ppdjax.primitives import bottom_to_top


def fit_groups(fit: bool, depth: bool, estimator: bool = False) -> tuple[str, ...]:
  """The fitted-box groups an evaluation has, least precise first; with an estimator, the
  most precise fit again, scored with it ("fit_est" or "fit_depth_est")."""
  fits = (("fit",) if fit else ()) + (("fit_depth",) if depth else ())
  if estimator and not fits:
    raise ValueError("the estimator reads fitted boxes: it needs fit or depth")
  return fits + ((fits[-1] + "_est",) if estimator else ())


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


def decode_groups(graphdef, state, obs, true, est_state=None, *, groups, camera,
                  est_graphdef=None, est_weight=1.0, true_shapes=False, depth_iterations=15,
                  image_fit=False):
  """The network's boxes and slot logits, and per fit group the fitted boxes
  (`fit.fit_boxes` from the network's; "fit" with `image_fit` then refined against the
  image, "fit_depth" against the depth image, `depth_fit`; the k-th logits go to the k-th
  fitted box from the bottom) and their logits
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
    fitted = fit_boxes(obs["voxels"], init=pred)
    refined = lambda **seen: refine_fitted(fitted, obs["voxels"], camera=camera,
                                           depth_iterations=depth_iterations, **seen)
    if "fit_depth" in groups:  # refined and snapped as `decompose` does (fit.refine_fitted)
      out["fitted"]["fit_depth"] = refined(depth=obs["depth"])
    if "fit" in groups:
      out["fitted"]["fit"] = refined(image=obs["image"]) if image_fit else fitted
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
