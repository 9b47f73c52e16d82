"""`python -m ppdjax.generate --config=ppdjax/configs/tiny.py --out=DIR`: a block-tower dataset."""

import os

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
_OUT = flags.DEFINE_string("out", None, "Dataset directory.", required=True)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  import jax
  jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/ppdjax/jax_cache"))
  from ppdjax.dataset import generation
  generation.generate(_CONFIG.value, _OUT.value)


if __name__ == "__main__":
  app.run(main)
