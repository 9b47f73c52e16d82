"""ppdjax: Physical Primitive Decomposition in JAX, with MuJoCo MJX physics."""

from ppdjax.primitives import Primitives

__all__ = ["Primitives"]
__version__ = "0.1.0"
