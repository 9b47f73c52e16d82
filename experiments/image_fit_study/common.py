"""Fresh towers for the image-fit scripts (`image_fit_study/run.py`,
`benchmarks/bench_image_fit.py`)."""

from __future__ import annotations

import jax
import numpy as np
from tqdm import tqdm

import ppdjax
from ppdjax.dataset import render


def fresh_towers(seed: int, count: int, size: int):
  """(towers, images (count, size, size, 3) uint8, voxel fit): towers of `seed` with random
  materials and textures rendered by MuJoCo through the dataset's camera and light
  (`dataset.render`), voxelized and fitted (`ppdjax.fit_boxes`)."""
  prims = ppdjax.sample_towers(seed, count)
  rng = np.random.default_rng(seed)
  with render.ObjectRenderer(size, size) as r:
    images = np.stack([r.render(jax.tree.map(lambda a, i=i: a[i], prims),
                                rng.integers(0, 5, 5), rng.integers(0, 256, 5), depth=False)[0]
                       for i in tqdm(range(count), desc="render")])
  return prims, images, ppdjax.fit_boxes(ppdjax.voxelize(prims))
