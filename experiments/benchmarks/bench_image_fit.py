"""Speed of the image fit (`infer.image_fit.refine_batch`) on a batch of fresh towers: its
two starts side by side against the same starts one after the other, and objects per chunk.

  python experiments/benchmarks/bench_image_fit.py --towers=64 --chunks=8,16,32,64

Towers of a seed nothing trains on are rendered through the dataset's camera and light
(`dataset.render`, 224² as the paper preset), voxelized and fitted (`ppdjax.fit_boxes`);
then, in one process and after compiling each variant once:
  * peer, "one after the other": each start of `image_fit.STARTS` run alone
    (`starts=(start,)`): what the fit cost before its starts ran side by side;
  * "one start": the sharp start alone;
  * "two starts, chunk C": `image_fit.STARTS` side by side (the default), C objects per
    chunk (`refine_batch(chunk=C)`);
  * "two starts, chunk C, every slot": the labels test all K box slots in every chunk
    (`refine_batch(slots=False)`, the fit before 2026-11-26, late evening), at the first
    chunk size;
  * with --sweeps, "two starts, chunk C, sweep AxB": fewer offsets scored per face
    (`refine_batch(sweep=(A, B))`; the default is `image_fit.SWEEP`);
  * with --tiles, "two starts, chunk C, tiles RxC" (each face scored on the pixels it can
    change, in tiles: `refine_batch(tile=(R, C))`, a CPU's default) or "..., window" (every
    pixel of the window: a GPU's default).
The rows without a tile use the machine's default (`refine_batch(tile="auto")`).
Each time is the median of --repeats calls on the whole batch; ratios are against the peer.
Agreement: per object, the face difference (mm) of each two-start row from the single
start it matches best, the largest over objects (the fit keeps one start's faces, so 0 at
the default sweep unless the chunking changes float rounding; another sweep is another
search).
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import numpy as np
from absl import app, flags
from tqdm import tqdm

from ppdjax.dataset import camera as camera_lib
from ppdjax.infer import image_fit
from ppdjax.metrics import box_faces

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # experiments/
from image_fit_study import common as image_fit_common  # noqa: E402

_TOWERS = flags.DEFINE_integer("towers", 64, "fresh towers (one batch)")
_SEED = flags.DEFINE_integer("seed", 4242, "their seed (never trained on)")
_SIZE = flags.DEFINE_integer("size", 224, "image size (the paper preset renders 224)")
_CHUNKS = flags.DEFINE_list("chunks", ["8", "16", "32", "64"], "objects per chunk to time")
_REPEATS = flags.DEFINE_integer("repeats", 3, "timed calls per variant (median)")
_SWEEPS = flags.DEFINE_list("sweeps", [], "other sweeps to time with two starts at the first "
                            "chunk size, as COARSExFINE offsets per face (default "
                            f"{image_fit.SWEEP[0]}x{image_fit.SWEEP[1]}), e.g. 17x9")
_TILES = flags.DEFINE_list("tiles", [], "tile sizes to time at the first chunk size, as "
                           "ROWSxCOLUMNS, or 'window' for none")
_OUT = flags.DEFINE_string("out", "experiments/results/bench_image_fit.json", "results JSON")


def timed(fn, repeats: int):
  """(result, median seconds) of `repeats` calls after one untimed (compiling) call."""
  out = jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    times.append(time.perf_counter() - t)
  return out, float(np.median(times))


def main(argv):
  del argv
  n, size = _TOWERS.value, _SIZE.value
  _, images, voxel_fit = image_fit_common.fresh_towers(_SEED.value, n, size)
  cam = camera_lib.camera_dict(size, size)
  chunks = [int(c) for c in _CHUNKS.value]
  fit = (lambda starts, chunk, sweep=image_fit.SWEEP, slots=True, tile="auto":
         lambda: image_fit.refine_batch(voxel_fit, images, cam, starts=starts, chunk=chunk,
                                        sweep=sweep, slots=slots, tile=tile))
  rows, faces = {}, {}
  singles = [timed(fit((start,), chunks[0]), _REPEATS.value) for start in image_fit.STARTS]
  rows["one after the other (peer)"] = sum(seconds for _, seconds in singles)
  rows["one start"] = singles[0][1]
  alone = np.stack([np.asarray(box_faces(out)) for out, _ in singles])  # (S, B, K, 6)
  for chunk in tqdm(chunks, desc="chunks"):
    name = f"two starts, chunk {chunk}"
    out, rows[name] = timed(fit(image_fit.STARTS, chunk), _REPEATS.value)
    faces[name] = np.asarray(box_faces(out))
  name = f"two starts, chunk {chunks[0]}, every slot"
  out, rows[name] = timed(fit(image_fit.STARTS, chunks[0], slots=False), _REPEATS.value)
  faces[name] = np.asarray(box_faces(out))
  for text in _SWEEPS.value:
    sweep = tuple(int(x) for x in text.split("x"))
    name = f"two starts, chunk {chunks[0]}, sweep {sweep[0]}x{sweep[1]}"
    out, rows[name] = timed(fit(image_fit.STARTS, chunks[0], sweep), _REPEATS.value)
    faces[name] = np.asarray(box_faces(out))
  for text in _TILES.value:
    tile = None if text == "window" else tuple(int(x) for x in text.split("x"))
    name = f"two starts, chunk {chunks[0]}, " + ("window" if tile is None else f"tiles {text}")
    out, rows[name] = timed(fit(image_fit.STARTS, chunks[0], tile=tile), _REPEATS.value)
    faces[name] = np.asarray(box_faces(out))
  valid = np.asarray(voxel_fit.valid, bool)[..., None]

  def difference_mm(f):  # per object, the single start it matches best; the worst object
    per_start = np.where(valid, np.abs(f[None] - alone), 0.0).max(axis=(-2, -1))
    return round(float(per_start.min(0).max()) * 1000, 3)
  peer_s = rows["one after the other (peer)"]
  result = {
      "towers": n, "size": size, "seed": _SEED.value,
      "rows": {name: {"seconds": round(s, 3), "objects_per_s": round(n / s, 1),
                      "speedup_vs_peer": round(peer_s / s, 2),
                      "max_face_difference_mm": (difference_mm(faces[name])
                                                 if name in faces else None)}
               for name, s in rows.items()},
      "machine": f"{jax.devices()[0].device_kind} ({jax.default_backend()}), "
                 f"{os.cpu_count()} CPU cores",
      "command": f"python experiments/benchmarks/bench_image_fit.py --towers={n} "
                 f"--seed={_SEED.value} --size={size} --chunks={','.join(map(str, chunks))} "
                 f"--repeats={_REPEATS.value}"
                 + (f" --sweeps={','.join(_SWEEPS.value)}" if _SWEEPS.value else "")
                 + (f" --tiles={','.join(_TILES.value)}" if _TILES.value else "")}
  os.makedirs(os.path.dirname(_OUT.value) or ".", exist_ok=True)
  with open(_OUT.value, "w") as f:
    json.dump(result, f, indent=1)
  lines = [f"Image fit of {n} fresh towers ({size}², seed {_SEED.value}) on "
           f"{result['machine']}:", "", "| variant | s per batch | objects/s | vs peer | "
           "max face difference vs peer (mm) |", "|---|--:|--:|--:|--:|"]
  for name, row in result["rows"].items():
    diff = "" if row["max_face_difference_mm"] is None else row["max_face_difference_mm"]
    lines.append(f"| {name} | {row['seconds']} | {row['objects_per_s']} | "
                 f"{row['speedup_vs_peer']}x | {diff} |")
  print("\n".join(lines + ["", result["command"]]))


if __name__ == "__main__":
  app.run(main)
