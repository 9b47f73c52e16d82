"""Tiny preset: the schema's defaults (`configs.schema`), which run on a laptop CPU in minutes,
with the data simulated by MuJoCo C."""

import ml_collections

from ppdjax.configs import schema


def get_config() -> ml_collections.ConfigDict:
  config = schema.default_config()
  # the data's trajectories by MuJoCo's C engine, the CPU's fast engine (docs/physics.md):
  # MJX's rollout is traced and compiled before its first step (docs/data.md, Presets).
  # Inference on a CPU selects with C anyway and refines through MJX, as for any data.
  config.data.backend = "mujoco"
  return config
