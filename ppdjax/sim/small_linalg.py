"""Linear algebra for the 6x6 systems of a free body's Newton solver, unrolled."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky_solve(a: jax.Array, b: jax.Array) -> jax.Array:
  """Solves a x = b for a small SPD matrix by an unrolled Cholesky factorisation.

  Plain arithmetic that XLA fuses into a few kernels, where `cho_factor`/`cho_solve` call
  a batched linear-algebra library per Newton iteration (measured in docs/physics.md).
  """
  return jnp.stack(cholesky_solve_entries(a, [b[i] for i in range(b.shape[0])]))


def cholesky_solve_entries(a, b) -> tuple:
  """`cholesky_solve` on entries: `a[i][j]` and `b[i]` are arrays of one shape (an
  array's rows, or nested tuples of a GPU kernel's per-lane values); returns x's entries."""
  n = len(b)
  low = [[None] * n for _ in range(n)]
  for j in range(n):
    diag = a[j][j] - sum(low[j][k] * low[j][k] for k in range(j))
    low[j][j] = jnp.sqrt(jnp.maximum(diag, 1e-30))
    for i in range(j + 1, n):
      low[i][j] = (a[i][j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
  y = [None] * n
  for i in range(n):
    y[i] = (b[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i]
  x = [None] * n
  for i in reversed(range(n)):
    x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
  return tuple(x)
