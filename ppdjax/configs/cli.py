"""The one override path of the command lines: `--config.<section>.<key>=<value>`.

Training and generation take a preset (`--config=ppdjax/configs/paper.py`) and override
it; commands that read a trained model (`evaluate`, `decompose`) override the config the
model was saved with. Either way the keys are the schema's (`configs.schema`).
"""

from __future__ import annotations

from absl import flags
from ml_collections import config_flags

from ppdjax.configs import schema


def define_model_overrides(sections: tuple[str, ...] = ("eval",)):
  """`--config.<section>.<key>=<value>` over a trained model's saved config (the schema's
  defaults stand in for it at parse time; only what is given on the command line counts)."""
  return config_flags.DEFINE_config_dict(
      "config", schema.default_config(),
      "Overrides of the model's saved settings, e.g. --config.eval.samples=64 "
      f"(sections: {', '.join(sections)}; keys: ppdjax/configs/schema.py).")


def model_overrides(sections: tuple[str, ...] = ("eval",)) -> dict[str, dict]:
  """The `--config.*` values given on the command line, by section; ConfigError for a key
  outside `sections`."""
  given = config_flags.get_override_values(flags.FLAGS["config"])
  out: dict[str, dict] = {s: {} for s in sections}
  for dotted, value in given.items():
    section, _, key = dotted.partition(".")
    if section not in sections:
      raise schema.ConfigError(f"--config.{dotted}: this command reads only "
                               f"{', '.join('config.' + s for s in sections)}")
    out[section][key] = value
  return out

