"""Decompose a block tower with the shipped model: load, one jitted call, a picture.

  python experiments/decompose_example.py                    # assets/ -> out/example.png
  python experiments/decompose_example.py --samples=64 --out=out/example.png

Loads the trained full model from assets/blocks_model (`ppdjax.load`) and the example
tower from assets/blocks_example.npz (a test-split tower: voxels, image, the four push
trajectories and its true boxes), decomposes it with the jitted `decompose` (density
samples simulated in MJX) and saves the input image beside the recovered boxes coloured
by density and the truth (`ppdjax.infer.example`).
"""

from __future__ import annotations

import numpy as np
from absl import app, flags

from ppdjax.infer.example import decompose_example

_MODEL = flags.DEFINE_string("model", "assets/blocks_model", "An exported model or training "
                             "workdir.")
_EXAMPLE = flags.DEFINE_string("example", "assets/blocks_example.npz", "The tower to decompose.")
_OUT = flags.DEFINE_string("out", "out/example.png", "The picture.")
_SAMPLES = flags.DEFINE_integer("samples", 512, "Density samples simulated per call.")


def main(argv):
  del argv
  r = decompose_example(_MODEL.value, _EXAMPLE.value, _OUT.value, _SAMPLES.value)
  print(f"recovered densities {np.round(r['densities'])} kg/m³ (true "
        f"{np.round(r['true_densities'])}); trajectory distance {r['distance_m'] * 1e3:.1f} mm; "
        f"{r['seconds'] * 1e3:.0f} ms per call; picture: {r['path']}")


if __name__ == "__main__":
  app.run(main)
