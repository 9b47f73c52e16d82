"""Where a row's Table 5 error comes from: its per-object records, by block count.

Reads the per-object records an evaluation keeps (`python -m ppdjax.evaluate ... --out=DIR`
saves them in DIR/partial) and, for one row and each block count, says how the squared
slot error spreads over the objects (the share of the worst 5 % and 1 %), how often the
arg-max slot is off by more than 5 slots, and how the errors go with the fit's worst face
error (objects split at the median of that face error).

  python experiments/table5_errors/run.py --eval=DIR --row="PPD+Fit+Sample" --faces=fit
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import app, flags

from ppdjax.eval import partial

_EVAL = flags.DEFINE_string("eval", None, "An evaluation's output folder.", required=True)
_ROW = flags.DEFINE_string("row", "PPD+Fit+Sample", "The row to break down.")
_FACES = flags.DEFINE_string("faces", "fit", "Whose face errors to relate it to (records' "
                             '("faces", NAME)), or "" for none.')
_OUT = flags.DEFINE_string("out", "", "Also write the breakdown as JSON here.")


def read_records(folder: str) -> dict:
  """Every saved batch of FOLDER/partial, concatenated in object order."""
  try:
    return partial.saved_records(os.path.join(folder, "partial"))
  except ValueError as e:
    raise app.UsageError(f"{e}: --eval names the output folder of `python -m "
                         "ppdjax.evaluate --keep_records`") from e


def breakdown(rec: dict, row: str, faces: str) -> dict:
  if ("guess", row) not in rec:
    rows = sorted({k[1] for k in rec if k[0] == "guess"})
    raise app.UsageError(f"no row {row!r} in the records; rows: {rows}")
  valid = rec[("true_valid",)].astype(bool)
  err = np.where(valid, rec[("guess", row)] - np.maximum(rec[("true_slot",)], 0), 0)
  sq = (err.astype(np.float64) ** 2).sum(-1)
  worst_box = np.abs(err).max(-1)
  # the worst face of each object's true boxes, mm (padded boxes hold NaN)
  face = np.nanmax(np.abs(rec[("faces", faces)]), (-2, -1)) * 1000 if faces else None
  out = {}
  for b in sorted(set(rec[("blocks",)].tolist())):
    sel = rec[("blocks",)] == b
    s = np.sort(sq[sel])[::-1]
    n, boxes = int(sel.sum()), int(valid[sel].sum())
    part = {"objects": n, "rmse": float(np.sqrt(s.sum() / boxes)),
            "share_worst_5pct": float(s[:max(1, n // 20)].sum() / max(s.sum(), 1e-12)),
            "share_worst_1pct": float(s[:max(1, n // 100)].sum() / max(s.sum(), 1e-12)),
            "rmse_without_worst_5pct": float(np.sqrt(s[max(1, n // 20):].sum() / boxes)),
            "objects_off_by_more_than_5_slots": float(np.mean(worst_box[sel] > 5))}
    if face is not None:
      f = face[sel]
      high = f > np.median(f)
      part["worst_face_mm_median"] = float(np.median(f))
      for name, part_sel in (("below", ~high), ("above", high)):
        boxes_in = valid[sel][part_sel].sum()
        part[f"rmse_faces_{name}_median"] = (float(np.sqrt(sq[sel][part_sel].sum() / boxes_in))
                                             if boxes_in else None)
    out[str(b)] = part
  return out


def main(argv):
  del argv
  rec = read_records(_EVAL.value)
  result = {"row": _ROW.value, "faces": _FACES.value,
            "by_blocks": breakdown(rec, _ROW.value, _FACES.value)}
  print(json.dumps(result, indent=1))
  if _OUT.value:
    with open(_OUT.value, "w") as f:
      json.dump(result, f, indent=1)


if __name__ == "__main__":
  app.run(main)
