"""Paper preset: the sizes of the ECCV 2018 paper, for a GPU."""

from ppdjax.configs import tiny


def get_config():
  config = tiny.get_config()
  config.name = "paper"
  return config
