"""Test setup: CPU backend, JAX's persistent compilation cache, shared fixtures."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

_CACHE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".jax_cache")
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def index(tree, i):
  """The i-th object of a batched pytree."""
  return jax.tree.map(lambda x: x[i], tree)


@pytest.fixture(scope="session")
def rng():
  return np.random.default_rng(1234)
