"""`python -m ppdjax.calibrate --images 'calib/*.jpg' --board 9x6 --square 0.025
--ground table.jpg --out camera.json`: the camera file `python -m ppdjax.track` reads.

--images: photographs of a printed checkerboard held at several tilts (a glob, or a
comma-separated list), at the resolution the camera films at; --board: its inner corners
per row x rows; --square: the printed side of one square, in the units of stickers.json
(docs/video.md: metres divided by the object's largest extent); --ground: one photograph, from
the camera's filming position, of the board lying flat on the table where the object will
stand (the world frame: `ppdjax.video.calibrate`). Writes intrinsics, distortion and
camera_from_world, prints the reprojection error, and draws the world's origin and axes
on the ground photograph (OUT with "_axes.png" for ".json"): the object's rest pose in
stickers.json is measured from them. Do not move or zoom the camera after
the ground photograph.
"""

from __future__ import annotations

import glob
import os

import cv2
import numpy as np
from absl import app, flags

from ppdjax.video import calibrate, files

_IMAGES = flags.DEFINE_string("images", None, "Board photographs: a glob or a comma list.",
                              required=True)
_BOARD = flags.DEFINE_string("board", None, "Inner corners, per row x rows (e.g. 9x6).",
                             required=True)
_SQUARE = flags.DEFINE_float("square", None, "Side of one square (m).", required=True)
_GROUND = flags.DEFINE_string("ground", None, "The board flat on the table, from the "
                              "filming position.", required=True)
_OUT = flags.DEFINE_string("out", "camera.json", "Camera file to write.")


def parse_board(text: str) -> tuple[int, int]:
  try:
    cols, rows = (int(v) for v in text.lower().split("x"))
  except ValueError:
    raise app.UsageError(f"--board must be COLSxROWS inner corners (e.g. 9x6), got {text!r}"
                         ) from None
  return cols, rows


def image_paths(spec: str) -> list[str]:
  """The files a glob or comma-separated list names (a name no glob matches is kept, so
  that reading it names it as missing)."""
  return sorted(p for part in spec.split(",") for p in (glob.glob(part) or [part]))


def main(argv):
  del argv
  board, paths = parse_board(_BOARD.value), image_paths(_IMAGES.value)
  if not _OUT.value.endswith(".json"):
    raise app.UsageError(f"--out must name a .json file, got {_OUT.value!r}")
  images = [files.read_image(p) for p in paths]
  table = files.read_image(_GROUND.value)
  try:
    cal = calibrate.calibrate_intrinsics(images, board, _SQUARE.value, names=paths)
    ground = calibrate.camera_from_ground(table, cal["intrinsics"], cal["distortion"], board,
                                          _SQUARE.value, name=_GROUND.value,
                                          image_size=cal["image_size"])
  except calibrate.CalibrationError as e:
    raise app.UsageError(str(e)) from None
  calibrate.write_camera(_OUT.value, cal["intrinsics"], ground, cal["distortion"],
                         rms_px=cal["rms_px"], image_size=cal["image_size"])
  axes = os.path.splitext(_OUT.value)[0] + "_axes.png"
  drawn = calibrate.draw_world_axes(table, cal["intrinsics"], cal["distortion"], ground,
                                    3 * _SQUARE.value)
  if not cv2.imwrite(axes, cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR)):
    raise app.UsageError(f"cannot write {axes}")
  height = np.linalg.inv(ground)[2, 3]
  print(f"board found in {len(cal['views'])} of {len(paths)} photographs; reprojection "
        f"error {cal['rms_px']:.2f} px; camera {height:.3f} m above the table -> {_OUT.value}, "
        f"the world's axes on the table: {axes}")


if __name__ == "__main__":
  app.run(main)
