"""`python -m ppdjax.train --config=ppdjax/configs/tiny.py --data=DIR --workdir=DIR`.

Trains (or resumes) the PPD network; see `ppdjax.training.loop.train_and_evaluate`.
"""

import json

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
_DATA = flags.DEFINE_string("data", None, "Dataset directory (python -m ppdjax.generate).",
                            required=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Where checkpoints, metrics and plots go.",
                               required=True)


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)  # orbax reports every save at INFO
  from ppdjax.training import loop, sharding
  sharding.maybe_initialize_distributed()
  metrics = loop.train_and_evaluate(_CONFIG.value, _DATA.value, _WORKDIR.value)
  print(json.dumps({"final_validation": metrics}, indent=1))


if __name__ == "__main__":
  app.run(main)
