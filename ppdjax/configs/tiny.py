"""Tiny preset: the schema's defaults (`configs.schema`), which run on a laptop CPU in minutes."""

import ml_collections

from ppdjax.configs import schema


def get_config() -> ml_collections.ConfigDict:
  return schema.default_config()
