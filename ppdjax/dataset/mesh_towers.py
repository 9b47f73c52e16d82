"""A user's mesh of blocks observed as the block towers are: the inputs of the towers' and
the video models (`python -m ppdjax.decompose --mesh ... --trajectory ...`).

The mesh is normalised upright (`load_object(upright=True)`: its z axis stays up, centred
and scaled to a 1 m largest extent, as the towers are), its parts become boxes
(`mesh_boxes.boxes_of_parts`), and the boxes are observed by the towers' own functions:
voxels (`voxels.voxelize`), an image from the towers' camera with each block's texture
(`render`, the model's `data.look`) and the depth image (`depth.render_depths`). The
tools' path (`tool_scene.observe`) turns a mesh onto its principal axes and films it with
the tools' camera, which lays a tower on its side and shows it as the towers' models never
saw one.
"""

from __future__ import annotations

import numpy as np

from ppdjax import primitives
from ppdjax.dataset import camera, depth, materials, render, voxels
from ppdjax.dataset.mesh_boxes import boxes_of_parts


def observe_tower(parts, part_materials, densities, seed: int, data) -> tuple[dict, object]:
  """({"voxels", "image", "depth"} as a towers dataset's sample holds them, the boxes
  (Primitives (K,), each with its part's density)) of upright-normalised `parts`.

  Args:
    parts: trimesh parts in the normalised upright frame (`load_object(upright=True)`).
    part_materials: a material name per part (`materials.ALL_MATERIAL_NAMES`).
    densities: kg/m^3 per part.
    seed: the textures' seed.
    data: the model's data section (its `image_size` and `look`).
  """
  truth, owner = boxes_of_parts(list(parts), list(densities))
  ids = np.asarray([materials.ALL_MATERIAL_NAMES.index(part_materials[o]) if o >= 0 else -1
                    for o in owner])
  shown = np.maximum(materials.look_ids(ids, data.get("look", "material")), 0)[None]
  seeds = np.random.default_rng(seed).integers(0, materials.TEXTURE_VARIANTS, shown.shape)
  size = int(data.image_size)
  batch = primitives.stack([truth])
  with render.BatchRenderer(size, size, 0, depth=False) as renderer:
    image, _ = renderer.render(batch, shown, seeds)
  obs = {"voxels": np.asarray(voxels.voxelize(batch))[0].astype(np.uint8),
         "image": np.asarray(image)[0],
         "depth": np.asarray(depth.render_depths(batch, camera.camera_dict(size, size)))[0]}
  return obs, truth
