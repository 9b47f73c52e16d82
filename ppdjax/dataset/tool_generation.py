"""The tools dataset's shards (paper Sec. 5.2): each tool observed from its own geometry.

`python -m ppdjax.generate --config=ppdjax/configs/tools.py --out=DIR` writes the towers'
format (`storage`), one sample per tool: its exact voxels (`meshes.voxelize_parts`), an
image and MuJoCo depth rendered from the parts (`tool_scene.render_tool`), trajectories
simulated from the parts (`tool_scene.simulate_tool`), and as labels the boxes of
`mesh_boxes.boxes_of_parts`, each with the material and density of the part it covers
most and the thickness of that part ("thickness": the thinnest side of its minimum
oriented bounding box, 0 for padded slots). "tower_id" holds the tool's index. Sample i is
a pure function of (seed, i): tool i is `tools.sample_tool(seed, i)`, or, in the rare case
its simulation diverges, the first of `sample_tool(seed, i + a * ATTEMPT_STRIDE)`,
a = 1, 2, ... that does not.

The data config's "tool_materials" (`materials_mode`) picks the labels of that geometry:
"category" (materials by category, a density per part: datasets made before the key) or
"plausible" (`tools.sample_plausible_tool`: one material and density per physical piece,
each material drawn from the part's plausible set). The meshes are the same in both.
"""

from __future__ import annotations

import numpy as np

from ppdjax import primitives
from ppdjax.conventions import PUSH_MAGNITUDES
from ppdjax.sim.pushes import Pushes
from ppdjax.dataset import render, storage, tool_scene, tools
from ppdjax.dataset.materials import ALL_MATERIAL_NAMES, TEXTURE_VARIANTS
from ppdjax.dataset.mesh_boxes import boxes_of_parts
from ppdjax.dataset.meshes import normalize

ATTEMPTS = 4
ATTEMPT_STRIDE = 1_000_000


MATERIAL_MODES = ("category", "plausible")


def materials_mode(cfg) -> str:
  """The realistic tools' labels: "category" (materials by category, a density per part;
  the value for data sections made before the key) or "plausible" (a material per physical
  piece from the part's plausible set, a density per piece: `tools.PLAUSIBLE_MATERIALS`)."""
  return _check_materials(str(cfg.get("tool_materials", "category")))


def _check_materials(mode: str) -> str:
  if mode not in MATERIAL_MODES:
    raise ValueError(f"tool_materials must be one of {MATERIAL_MODES}, got {mode!r}")
  return mode


def density_variants(tool: tools.Tool, seed: int, index: int, configs: int) -> list:
  """The `configs` density configurations of tool `index` of `seed`: the tool itself, then
  each other with every piece's slot drawn again (`tools.with_new_slots`, from (seed, index,
  c)), as the dataset stores them."""
  return [tool] + [tools.with_new_slots(tool, np.random.default_rng([seed, index, c]))
                   for c in range(1, configs)]


def tool_samples(seed: int, index: int, image_size: int, steps: int, configs: int = 1,
                 force: float = tool_scene.TOOL_PUSH_FORCE, materials: str = "category",
                 push: str = "fixed") -> list[dict[str, np.ndarray]]:
  """The arrays of tool `index` (one row of each storage field but "split", plus
  "thickness") under `configs` density configurations: the first with the tool's own
  slots, each other with every piece's slot drawn again within its material's range
  (`tools.with_new_slots`, from (seed, index, c)). Geometry, materials and textures are
  shared, so voxels, image, depth and boxes are made once; each configuration has its own
  trajectories and box densities. The pushes are the paper's four directions at `force`
  newtons, or with `push` "by_volume" at the force `tool_scene.push_force_for` gives the
  tool's volume (the rows then hold it: "push_magnitudes" (P,)); `materials` is the
  labelling (`MATERIAL_MODES`, see `materials_mode`). Every row holds the tool's category
  ("category", an index into `tools.CATEGORIES`)."""
  draw = (tools.sample_plausible_tool if _check_materials(materials) == "plausible"
          else tools.sample_tool)  # the same meshes; the labels before anything is observed
  rng = np.random.default_rng([seed, index])
  for attempt in range(ATTEMPTS):
    tool = draw(seed, index + attempt * ATTEMPT_STRIDE)
    parts, _ = normalize(list(tool.parts))
    tex_seeds = rng.integers(0, TEXTURE_VARIANTS, len(parts))
    variants = density_variants(tool, seed, index, configs)
    pushes = tool_scene.tool_pushes(tool_scene.push_force_for(
        force, sum(abs(p.volume) for p in parts), push))
    try:
      obs = tool_scene.observe(parts, tool.materials, tool.densities, tex_seeds,
                               image_size=image_size, steps=steps, pushes=pushes)
      trajectories = [obs["trajectories"]] + [
          tool_scene.simulate_tool(parts, v.densities, pushes, steps=steps).astype(np.float32)
          for v in variants[1:]]
      break
    except RuntimeError:
      continue
  else:
    raise RuntimeError(f"tool {index} of seed {seed}: every attempt diverged")
  prims, owner = boxes_of_parts(parts, tool.densities)
  ids = np.asarray([ALL_MATERIAL_NAMES.index(tool.materials[o]) if o >= 0 else -1
                    for o in owner])
  fields = {f: np.asarray(getattr(prims, f)) for f in primitives.FIELDS}
  # a label, not an observation: how thin the part under each box is (a blade's thickness
  # is far below a voxel, so the voxels cannot tell it)
  thickness = np.where(owner >= 0, tools.part_thicknesses(parts)[np.maximum(owner, 0)], 0.0)
  out = []
  for v, traj in zip(variants, trajectories):
    density = np.where(owner >= 0, v.densities[np.maximum(owner, 0)], fields["density"])
    out.append({**obs, **fields, "trajectories": traj, "density": density.astype(np.float32),
                "materials": ids, "thickness": thickness.astype(np.float32),
                "category": np.int64(tools.CATEGORIES.index(tool.category)),
                "tower_id": np.int64(index)})
    if push == "by_volume":  # each tool's own force, which the candidates' rollouts need
      out[-1][PUSH_MAGNITUDES] = np.asarray(pushes.magnitudes, np.float32)
  return out


def tool_sample(seed: int, index: int, image_size: int, steps: int,
                force: float = tool_scene.TOOL_PUSH_FORCE, materials: str = "category",
                push: str = "fixed") -> dict[str, np.ndarray]:
  """The arrays of tool `index` under its own densities (the first of `tool_samples`)."""
  return tool_samples(seed, index, image_size, steps, force=force, materials=materials,
                      push=push)[0]


def _one(args):
  return tool_samples(*args)


class ToolWorkers:
  """Makes tool samples in `workers` processes (0: this one); a context manager."""

  def __init__(self, workers: int):
    self._pool = render.cpu_process_pool(workers) if workers > 0 else None

  def map(self, jobs: list, work=_one) -> list:
    """[work(job) for job in jobs], in the workers (`work`: a module-level function)."""
    return self._pool.map(work, jobs) if self._pool else [work(j) for j in jobs]

  def imap(self, jobs: list, work=_one):
    """`map`'s results one at a time, in order, as they are done (for a progress bar)."""
    return self._pool.imap(work, jobs) if self._pool else (work(j) for j in jobs)

  def close(self):
    if self._pool is not None:
      self._pool.close()
      self._pool.join()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()


def configs_per_tool(cfg) -> int:
  """Density configurations per tool geometry (1 for data sections made before the key)."""
  return int(cfg.get("configs_per_tool", 1))


PROTOCOLS = ("realistic", "paper")


def protocol(cfg) -> str:
  """"realistic" (this module: the tool's own parts are the body) or "paper"
  (`tool_paper`: the tool's boxes are the body, materials uniform over Table 1's five)."""
  return str(cfg.get("tool_protocol", "realistic"))


def push_force(cfg) -> float:
  """The pushes' magnitude in newtons (`tool_scene.TOOL_PUSH_FORCE` for data sections made
  before the key, and for the towers' models)."""
  return float(cfg.get("tool_push_force", tool_scene.TOOL_PUSH_FORCE))


def push_mode(cfg) -> str:
  """"fixed" (every tool pushed with `push_force`: data sections made before the key) or
  "by_volume" (`tool_scene.push_force_for`: the force scales with the tool's volume)."""
  return str(cfg.get("tool_push", "fixed"))


def tool_pushes(cfg, parts) -> Pushes:
  """The pushes a tool of normalised `parts` gets under the data section `cfg`."""
  volume = sum(abs(p.volume) for p in parts)
  return tool_scene.tool_pushes(tool_scene.push_force_for(push_force(cfg), volume,
                                                          push_mode(cfg)))


def generate_shard(cfg, seed: int, shard: int, workers: ToolWorkers) -> dict[str, np.ndarray]:
  """All arrays of one shard of tools."""
  first = shard * cfg.tools_per_shard
  count = min(cfg.tools_per_shard, cfg.num_tools - first)
  configs = configs_per_tool(cfg)
  jobs = [(seed, i, cfg.image_size, cfg.steps, configs, push_force(cfg), materials_mode(cfg),
           push_mode(cfg))
          for i in range(first, first + count)]
  rows = [row for tool in workers.map(jobs) for row in tool]
  arrays = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
  arrays["split"] = storage.split_of(arrays["tower_id"], tuple(cfg.split_fractions))
  return arrays
