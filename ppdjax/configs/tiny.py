"""Tiny preset: runs on a laptop CPU in a few minutes."""

import ml_collections


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "tiny"
  config.seed = 0
  # Physics demo: one random tower under the paper's four pushes.
  config.demo = ml_collections.ConfigDict()
  config.demo.num_blocks = 4  # 2..5
  config.demo.steps = 256
  config.demo.backend = "mjx"  # the engine whose trajectories are shown
  config.demo.reference_backend = "mujoco"  # compared against; "" to skip
  # Block-tower dataset (python -m ppdjax.generate).
  config.data = ml_collections.ConfigDict()
  config.data.num_towers = 16
  config.data.towers_per_shard = 4
  config.data.configs_per_tower = 8
  config.data.image_size = 64
  config.data.steps = 256
  config.data.rotate = 0.0  # radians; > 0 adds the paper's rotation noise (tools pretraining)
  config.data.size_noise = 0.0
  config.data.backend = "mjx"  # the engine inference uses; "mujoco" makes a marked C variant
  config.data.split_fractions = (0.8, 0.1, 0.1)
  config.data.render_workers = 0  # processes rendering in parallel (0: this process)
  return config
