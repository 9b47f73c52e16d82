"""Resumable generation of a block-tower dataset (`python -m ppdjax.generate` calls it).

Shard s is a pure function of (config, s): its towers come from
`default_rng([seed, s])`, so an interrupted run resumes at the first incomplete shard and
ends byte-identical to an uninterrupted one (on the same machine and software).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
import time

import jax
import ml_collections
import numpy as np
from tqdm.auto import tqdm

from ppdjax import primitives
from ppdjax.dataset import (camera, card, depth, hollow, materials, render, storage,
                            tool_generation, tool_paper, tool_scene, towers, voxels)
from ppdjax.sim.pushes import default_pushes, pendulum_strike
from ppdjax.sim.rollout_mjx import settings_for
from ppdjax.sim.simulate import BACKENDS, simulate


# Where the "depth" arrays come from; part of a dataset's identity (config.json), so that
# generation never resumes over shards whose depth came from MuJoCo's GL pass (before it).
DEPTH_SOURCE = "exact ray cast of the boxes and the ground (ppdjax.dataset.depth)"
TOOL_DEPTH_SOURCE = "MuJoCo's depth pass of the tool's parts (ppdjax.dataset.tool_scene)"


def pushes_record(pushes) -> dict:
  """The pushes as the manifest stores them (`storage.Dataset.pushes` reads them back)."""
  record = {"sources": np.asarray(pushes.sources).tolist(),
            "targets": np.asarray(pushes.targets).tolist(),
            "magnitudes": np.asarray(pushes.magnitudes).tolist(), "duration": pushes.duration}
  if pushes.is_strike:
    record.update(striker_masses=np.asarray(pushes.striker_masses).tolist(),
                  restitution=float(pushes.restitution))
  return record


def check_config(cfg) -> None:
  """Raises ValueError naming the first bad value of the `data` section."""
  if kind_of(cfg) not in KINDS:
    raise ValueError(f"config.data.kind must be one of {KINDS}, got {cfg.kind!r}")
  if kind_of(cfg) == "tools":
    rules = [("num_tools", cfg.num_tools >= 1), ("tools_per_shard", cfg.tools_per_shard >= 1),
             ("configs_per_tool", tool_generation.configs_per_tool(cfg) >= 1),
             ("tool_protocol", tool_generation.protocol(cfg) in tool_generation.PROTOCOLS),
             ("tool_push", tool_generation.push_mode(cfg) in tool_scene.PUSH_MODES),
             ("tool_materials", str(cfg.get("tool_materials", "category"))
              in tool_generation.MATERIAL_MODES),
             ("backend", cfg.backend in BACKENDS),
             # above 1e4 N MuJoCo's solver diverges on some tools (tool_scene.TOOL_PUSH_FORCE)
             ("tool_push_force", 0 < tool_generation.push_force(cfg) <= 1e4)]
  else:
    rules = [("num_towers", cfg.num_towers >= 1),
             ("block_counts", kind_of(cfg) != "pendulum" or (
                 len(cfg.block_counts) >= 1 and all(2 <= n <= 5 for n in cfg.block_counts))),
             ("towers_per_shard", cfg.towers_per_shard >= 1),
             ("configs_per_tower", cfg.configs_per_tower >= 1),
             ("rotate", 0 <= cfg.rotate <= np.pi), ("size_noise", 0 <= cfg.size_noise < 1),
             ("backend", cfg.backend in BACKENDS),
             ("look", cfg.get("look", "material") in materials.LOOKS),
             ("hollow", 0.0 <= cfg.get("hollow", 0.0) <= 1.0)]
  rules += [("render_workers", 0 <= cfg.render_workers <= 256),
            ("image_size", 16 <= cfg.image_size <= 1024), ("steps", cfg.steps >= 1),
            ("split_fractions", len(cfg.split_fractions) == 3
             and abs(sum(cfg.split_fractions) - 1) < 1e-6 and min(cfg.split_fractions) >= 0)]
  for key, ok in rules:
    if not ok:
      raise ValueError(f"config.data.{key} has a bad value: {cfg[key]!r}")


KINDS = ("towers", "tools", "pendulum")


def kind_of(cfg) -> str:
  """"towers" (the default), "tools" (`tool_generation`) or "pendulum" (towers of the real
  blocks' materials, struck by the pendulum's ball: the paper's real setup, Sec. 5.3)."""
  return cfg.get("kind", "towers")


def pushes_of(cfg):
  """The pushes a dataset of this data section is recorded under."""
  if kind_of(cfg) == "tools":
    return tool_scene.tool_pushes(tool_generation.push_force(cfg))
  return pendulum_strike() if kind_of(cfg) == "pendulum" else default_pushes()


def _plan(cfg):
  """(objects, objects per shard, samples per object, unit) of the data section."""
  if kind_of(cfg) == "tools":
    return cfg.num_tools, cfg.tools_per_shard, tool_generation.configs_per_tool(cfg), "tool"
  return cfg.num_towers, cfg.towers_per_shard, cfg.configs_per_tower, "tower"


def _workers(cfg):
  """What makes a shard's observations: tool processes, or the towers' renderer."""
  if kind_of(cfg) == "tools":
    return tool_generation.ToolWorkers(cfg.render_workers)
  return render.BatchRenderer(cfg.image_size, cfg.image_size, cfg.render_workers, depth=False)


def bytes_per_sample(cfg) -> int:
  return (32 ** 3 + cfg.image_size ** 2 * 7 + 4 * cfg.steps * 7 * 4 + 5 * 11 * 4 + 32)


def generate_shard(cfg, seed: int, shard: int, renderer) -> dict[str, np.ndarray]:
  """All arrays of one shard (towers × configurations)."""
  rng = np.random.default_rng([seed, shard])
  first = shard * cfg.towers_per_shard
  count = min(cfg.towers_per_shard, cfg.num_towers - first)
  pendulum = kind_of(cfg) == "pendulum"
  prims, ids = [], []
  for _ in range(count):
    blocks = int(rng.choice(cfg.block_counts)) if pendulum else cfg.get("num_blocks", 0) or None
    p, m = towers.sample_configurations(rng, cfg.configs_per_tower, num_blocks=blocks,
                                        rotate=cfg.rotate, size_noise=cfg.size_noise,
                                        material_set="real" if pendulum else "paper")
    prims.append(p)
    ids.append(m)
  vox = voxels.voxelize(primitives.stack([jax.tree.map(lambda x: x[0], p) for p in prims]))
  prims = primitives.stack([jax.tree.map(lambda x, c=c: x[c], p) for p in prims
                        for c in range(cfg.configs_per_tower)])
  ids = np.concatenate(ids)
  scales = {}
  if cfg.get("hollow", 0.0) > 0:  # shells around cores: mean densities, their inertia
    prims, _ = hollow.hollow_blocks(rng, prims, ids, cfg.hollow)
    scales["inertia_scale"] = np.asarray(prims.inertia_scale)
  tex_seeds = rng.integers(0, materials.TEXTURE_VARIANTS, ids.shape)
  looks = materials.look_ids(ids, cfg.get("look", "material"))  # what each block shows
  images, _ = renderer.render(prims, np.maximum(looks, 0), tex_seeds)
  depths = np.asarray(depth.render_depths(prims, camera.camera_dict(cfg.image_size,
                                                                    cfg.image_size)))
  traj = np.asarray(simulate(prims, pushes_of(cfg), steps=cfg.steps, backend=cfg.backend),
                    np.float32)
  tower_id = np.repeat(np.arange(first, first + count), cfg.configs_per_tower).astype(np.int64)
  return {"voxels": np.repeat(vox, cfg.configs_per_tower, 0),
          "image": images, "depth": depths, "trajectories": traj,
          **{f: np.asarray(getattr(prims, f)) for f in primitives.FIELDS},
          "materials": ids, "tower_id": tower_id, **scales,
          "split": storage.split_of(tower_id, tuple(cfg.split_fractions))}


def _tools_engine(cfg) -> str:
  """What made a tools dataset's trajectories, in words (its manifest's "engine")."""
  force = f"pushes of {tool_generation.push_force(cfg):g} N" + (
      f" x the tool's volume / {tool_scene.REFERENCE_VOLUME:g} m^3"
      if tool_generation.push_mode(cfg) == "by_volume" else "")
  if tool_generation.protocol(cfg) == "paper":
    return f"the paper's protocol: the tool's boxes simulated as towers ({cfg.backend}), {force}"
  return f"MuJoCo C on the parts' convex pieces, {force}"


def generate(config, out: str, progress: bool = True) -> dict:
  """Generates (or resumes) the dataset of `config` in `out`; returns the manifest."""
  cfg = config.data
  check_config(cfg)
  os.makedirs(out, exist_ok=True)
  config_path = os.path.join(out, "config.json")
  # a dataset depends on the seed, the data section and the depth source only (not on
  # model or train); tools' depth is MuJoCo's depth pass of the parts
  source = TOOL_DEPTH_SOURCE if kind_of(cfg) == "tools" else DEPTH_SOURCE
  text = ml_collections.ConfigDict({"name": config.name, "seed": config.seed,
                                    "data": config.data.to_dict(), "depth": source}
                                   ).to_json_best_effort(sort_keys=True, indent=1)
  if os.path.exists(config_path):
    with open(config_path) as f:
      if f.read() != text:
        raise ValueError(f"{out} holds a dataset made with another config ({config_path}); "
                         "use a new directory")
  else:
    free = shutil.disk_usage(out).free
    objects, _, per_object, _ = _plan(cfg)
    need = bytes_per_sample(cfg) * objects * per_object
    if need > free:
      raise OSError(f"not enough disk space in {out}: the dataset needs about "
                    f"{need / 1e9:.2f} GB, {free / 1e9:.2f} GB are free")
    with open(config_path, "w") as f:
      f.write(text)

  objects, per_shard, _, unit = _plan(cfg)
  num_shards = -(-objects // per_shard)
  names = [f"shard-{s:05d}" for s in range(num_shards)]
  sums = [storage.shard_complete(os.path.join(out, n)) for n in names]
  todo = [s for s in range(num_shards) if sums[s] is None]
  bar = tqdm(total=objects, unit=unit, disable=not progress, desc="generate")
  bar.update(objects - sum(min(per_shard, objects - s * per_shard) for s in todo))
  make_shard = generate_shard
  if unit == "tool":
    make_shard = (tool_generation.generate_shard if tool_generation.protocol(cfg) == "realistic"
                  else functools.partial(tool_paper.generate_shard, pushes=pushes_of(cfg)))
  t0 = time.perf_counter()
  if todo:
    with _workers(cfg) as workers:
      for s in todo:
        arrays = make_shard(cfg, config.seed, s, workers)
        sums[s] = storage.write_shard(os.path.join(out, names[s]), arrays)
        bar.update(len(np.unique(arrays["tower_id"])))
  bar.close()
  counts = []
  for s, name in enumerate(names):
    split = np.load(os.path.join(out, name, "split.npy"))
    counts.append({"name": name, "samples": int(len(split)), "files": sums[s],
                   "splits": {k: int((split == v).sum()) for k, v in storage.SPLITS.items()}})
  manifest = {
      "format_version": storage.FORMAT_VERSION, "config": json.loads(text), "seed": config.seed,
      "kind": kind_of(cfg), f"{unit}s": objects, "samples": sum(c["samples"] for c in counts),
      "splits": {k: sum(c["splits"][k] for c in counts) for k in storage.SPLITS},
      "engine": {"backend": cfg.backend,
                 "precision": "float64 (stored float32)" if cfg.backend == "mujoco" else "float32",
                 # the JAX engine's settings (inference reads "mujoco" data through MJX)
                 "settings": dataclasses.asdict(settings_for(cfg.backend)),
                 **({"tools": _tools_engine(cfg)} if unit == "tool" else {})},
      "pushes": pushes_record(pushes_of(cfg)),
      "camera": camera.camera_dict(cfg.image_size, cfg.image_size),
      "depth": source,
      "shards": counts,
  }
  with open(os.path.join(out, "manifest.json"), "w") as f:
    json.dump(manifest, f, indent=1, sort_keys=True)
  card.write_card(out)
  if progress:
    print(f"{manifest['samples']} samples in {num_shards} shards at {out} "
          f"({time.perf_counter() - t0:.0f} s this run); card: {out}/card.md")
  return manifest


def generate_fresh(config, out: str, towers: int, seed: int):
  """A test split of `towers` towers of `seed` (one never used for training) made as
  `config`'s dataset, one shard, rendered in this process: fresh data for benchmarks and
  studies. Returns the opened split (`storage.Dataset`)."""
  config = ml_collections.ConfigDict(config.to_dict())
  config.seed = seed
  config.data.num_towers = config.data.towers_per_shard = towers
  config.data.split_fractions = (0.0, 0.0, 1.0)
  config.data.render_workers = 0
  generate(config, out, progress=False)
  return storage.open_dataset(out, "test")
