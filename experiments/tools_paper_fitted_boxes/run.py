"""How far a reader that knew each box's mass exactly would get on the network's boxes.

Under the paper's protocol a box's density is its mass over its volume. The trajectories
give mass (true boxes +Sample+Refine read 98 % of slots exactly), so a reader on the
network's boxes reads, at best, true mass / network volume. This prints that reading's
top-1 and RMSE, and the network's volume error by the true box's thinnest side.

  python experiments/tools_paper_fitted_boxes/run.py --model=assets/tools_paper_model \
      --data=DATASET [--out=results.json]
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from ppdjax.conventions import density_to_slot
from ppdjax.dataset.storage import Dataset
from ppdjax.primitives import bottom_to_top
from ppdjax.training import checkpoints

_MODEL = flags.DEFINE_string("model", "assets/tools_paper_model", "Trained model.")
_DATA = flags.DEFINE_string("data", None, "A paper-protocol tools dataset.", required=True)
_OUT = flags.DEFINE_string("out", None, "Where to write the results (JSON).")
THIN = ((0.0, 0.01), (0.01, 0.03), (0.03, 0.1), (0.1, 1.0))  # m, normalised tools


def main(_):
  model, _ = checkpoints.load(_MODEL.value)
  data = Dataset(_DATA.value, split="test")
  decode = jax.jit(lambda obs: model.decode(obs)[0])
  ratio, err, thin = [], [], []
  for start in range(0, len(data), 64):
    rows = [data[i] for i in range(start, min(len(data), start + 64))]
    obs = {k: jnp.asarray(np.stack([r[k] for r in rows]))
           for k in ("voxels", "image", "trajectories")}
    true = bottom_to_top(jax.tree.map(lambda *x: jnp.stack(x), *[r["primitives"] for r in rows]))
    pred = bottom_to_top(decode(obs))
    both = np.asarray(pred.valid & true.valid)
    vp = 8 * np.prod(np.asarray(pred.half_size), -1)[both]
    vt = 8 * np.prod(np.asarray(true.half_size), -1)[both]
    rho = np.asarray(true.density)[both]
    read = np.clip(rho * vt / vp, 100.0, 10_000.0)  # true mass / the network's volume
    ratio += list(vp / vt)
    err += list(np.asarray(density_to_slot(jnp.asarray(read)))
                - np.asarray(density_to_slot(jnp.asarray(rho))))
    thin += list(2 * np.asarray(true.half_size).min(-1)[both])
  ratio, err, thin = map(np.asarray, (ratio, err, thin))
  out = {"boxes": int(len(err)), "objects": len(data),
         "volume_error_median": float(np.median(np.abs(ratio - 1))),
         "volume_error_p90": float(np.percentile(np.abs(ratio - 1), 90)),
         "mass_exact_top1": 100 * float(np.mean(err == 0)),
         "mass_exact_within1": 100 * float(np.mean(np.abs(err) <= 1)),
         "mass_exact_rmse": float(np.sqrt(np.mean(err ** 2))), "by_thinnest_side": {}}
  for lo, hi in THIN:
    m = (thin >= lo) & (thin < hi)
    if m.any():
      out["by_thinnest_side"][f"{lo}-{hi} m"] = {
          "boxes": int(m.sum()), "volume_error_median": float(np.median(np.abs(ratio[m] - 1))),
          "mass_exact_top1": 100 * float(np.mean(err[m] == 0)),
          "mass_exact_rmse": float(np.sqrt(np.mean(err[m] ** 2)))}
  print(json.dumps(out, indent=1))
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      json.dump(out, f, indent=1)


if __name__ == "__main__":
  app.run(main)
