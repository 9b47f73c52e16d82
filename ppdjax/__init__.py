"""ppdjax: Physical Primitive Decomposition in JAX, with MuJoCo MJX physics."""

import os

# MuJoCo picks its OpenGL platform when it is first imported: headless EGL unless the
# user chose otherwise (ppdjax.render needs it; physics does not).
os.environ.setdefault("MUJOCO_GL", "egl")

from ppdjax.primitives import Primitives  # noqa: E402


def load(workdir: str, which: str = "best"):
  """(model, config) of a training workdir; see `ppdjax.checkpoints.load`."""
  from ppdjax import checkpoints
  return checkpoints.load(workdir, which)


__all__ = ["Primitives", "load"]
__version__ = "0.1.0"
