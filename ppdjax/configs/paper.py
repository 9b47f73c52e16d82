"""Paper preset: the sizes of the ECCV 2018 paper, for a GPU."""

from ppdjax.configs import tiny


def get_config():
  config = tiny.get_config()
  config.name = "paper"
  # 10,000 towers x 8 configurations: the paper gives no count; 80k samples keep each of
  # the 100 density slots in ~2,000 training blocks.
  config.data.num_towers = 10_000
  config.data.towers_per_shard = 250
  config.data.image_size = 224
  config.data.render_workers = 12
  return config
