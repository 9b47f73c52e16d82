"""The image's side of the image fit: colour-edge strengths between neighbouring pixels
(integers, so that sums compare exactly), blurred copies for wider basins, and the edge
score of a label image against them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

EDGE_LEVELS = 1024  # integer steps per unit of colour difference


def edge_strength(image_HW3) -> tuple[jax.Array, jax.Array]:
  """Colour differences between each pixel and its left neighbour (H, W) and its upper
  neighbour (H, W), 0 on the first column / row: the Euclidean distance of RGB in [0, 1],
  in integer steps of 1 / EDGE_LEVELS (integer sums compare exactly: `sweep_faces` looks
  for runs of equal scores)."""
  img = jnp.asarray(image_HW3)
  scale = 1.0 / 255.0 if jnp.issubdtype(img.dtype, jnp.integer) else 1.0
  img = img.astype(jnp.float32) * scale
  steps = lambda diff: jnp.round(jnp.linalg.norm(diff, axis=-1) * EDGE_LEVELS).astype(jnp.int32)
  across, down = steps(img[:, 1:] - img[:, :-1]), steps(img[1:] - img[:-1])
  return jnp.pad(across, ((0, 0), (1, 0))), jnp.pad(down, ((1, 0), (0, 0)))


def blur_strength(strength_HW, sigma: float) -> jax.Array:
  """Edge strengths spread by a Gaussian of `sigma` pixels (integers still)."""
  r = max(1, int(np.ceil(3 * sigma)))
  g = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
  g = jnp.asarray(g / g.sum(), jnp.float32)
  x = strength_HW.astype(jnp.float32)
  x = jax.vmap(lambda row: jnp.convolve(row, g, mode="same"))(x)
  x = jax.vmap(lambda col: jnp.convolve(col, g, mode="same"), 1, 1)(x)
  return jnp.round(x).astype(jnp.int32)


def edge_score(labels_HW, across_HW, down_HW) -> jax.Array:
  """Minus the colour difference summed over neighbouring pixels whose labels differ
  (lower is better: the outline lies on the image's edges)."""
  cut_across = jnp.pad(labels_HW[:, 1:] != labels_HW[:, :-1], ((0, 0), (1, 0)))
  cut_down = jnp.pad(labels_HW[1:] != labels_HW[:-1], ((1, 0), (0, 0)))
  return -(jnp.sum(jnp.where(cut_across, across_HW, 0))
           + jnp.sum(jnp.where(cut_down, down_HW, 0)))
