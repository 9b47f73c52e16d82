"""`python -m ppdjax.train_estimator --config=ppdjax/configs/tiny.py --workdir=DIR`.

Trains (or resumes) the density estimator on simulated towers; see
`ppdjax.training.estimator.train_estimator`. No dataset is needed.
"""

import json

from absl import app, flags
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", "ppdjax/configs/tiny.py", "Preset file.")
_WORKDIR = flags.DEFINE_string("workdir", None, "Where the estimator and its metrics go.",
                               required=True)
_MAX_SECONDS = flags.DEFINE_float("max_seconds", 0.0,
                                  "> 0: save and stop after this long (run again to resume).")


def main(argv):
  del argv
  from ppdjax.training.estimator import train_estimator
  print(json.dumps(train_estimator(_CONFIG.value, _WORKDIR.value,
                                   max_seconds=_MAX_SECONDS.value), indent=1))


if __name__ == "__main__":
  app.run(main)
