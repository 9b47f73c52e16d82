"""Tools preset (paper Sec. 5.2): the procedural tools dataset, the paper preset's network.

`python -m ppdjax.generate --config=ppdjax/configs/tools.py --out=DIR` makes the tools
dataset (`ppdjax.dataset.tool_generation`). The paper had 204 tools; procedural ones are
free, so 2,000 (paper's split fractions), each observed once (one pose: lying on the
ground in the normalised frame). Override data.num_tools for a smaller set.
"""

from ppdjax.configs import paper


def get_config():
  config = paper.get_config()
  config.name = "tools"
  config.data.kind = "tools"
  config.data.num_tools = 2_000
  config.data.tools_per_shard = 250
  config.data.render_workers = 12  # processes: each tool's boxes take about 1 s of a core
  config.data.backend = "mujoco"  # tools are simulated by MuJoCo C from their own parts
  return config
