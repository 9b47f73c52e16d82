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
  return config
