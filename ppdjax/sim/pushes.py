"""The pushes that set objects moving: the paper's four, where each acts, and its wrench.

Push convention (docs/physics.md): a push has a source point and a target point in the
object frame at rest (object axes = world axes, origin = object-frame origin). The force,
of the given magnitude, points from source to target and acts, for `duration` steps, at
the first point where the ray source -> target meets a valid box. If the ray misses every
box (an object that does not contain its own origin, e.g. an L shape seen edge-on), the
force acts at the target itself. A force at a point is applied as force plus torque about
the centre of mass (MuJoCo's `xfrc_applied`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax.primitives import Primitives, ray_box_hits
from ppdjax.sim.mass import MassProperties, mass_properties

PAPER_FORCE = 1e5  # N, applied for one step of 1/300 s (impulse ~333 N s)


@struct.dataclass
class Pushes:
  """P pushes, each a force of `magnitude` from `source` towards `target` (object frame).

  Attributes:
    sources: (P, 3) metres, relative to the object-frame origin at rest.
    targets: (P, 3) metres, same frame.
    magnitudes: (P,) newtons.
    duration: steps during which each force acts (static).
  """

  sources: jax.Array
  targets: jax.Array
  magnitudes: jax.Array
  duration: int = struct.field(pytree_node=False, default=1)

  @property
  def num(self) -> int:
    return int(np.shape(self.magnitudes)[0])

  def validate(self) -> "Pushes":
    """Raises ValueError naming the field for wrong shapes, NaN/inf or bad values."""
    sources, targets, mags = (np.asarray(x) for x in (self.sources, self.targets,
                                                       self.magnitudes))
    if sources.ndim != 2 or sources.shape[1] != 3:
      raise ValueError(f"Pushes.sources: expected shape (P, 3), got {sources.shape}")
    p = sources.shape[0]
    if targets.shape != (p, 3):
      raise ValueError(f"Pushes.targets: expected shape ({p}, 3), got {targets.shape}")
    if mags.shape != (p,):
      raise ValueError(f"Pushes.magnitudes: expected shape ({p},), got {mags.shape}")
    for name, a in (("sources", sources), ("targets", targets), ("magnitudes", mags)):
      if not np.all(np.isfinite(a)):
        raise ValueError(f"Pushes.{name}: contains NaN or inf")
    if np.any(mags < 0):
      raise ValueError("Pushes.magnitudes: negative magnitude")
    if np.any(np.linalg.norm(targets - sources, axis=1) == 0):
      raise ValueError("Pushes.sources: a source coincides with its target (no direction)")
    if not isinstance(self.duration, (int, np.integer)) or self.duration < 1:
      raise ValueError(f"Pushes.duration: expected an int >= 1, got {self.duration!r}")
    return self


def default_pushes(magnitude: float = PAPER_FORCE) -> Pushes:
  """The paper's four pushes: sources (±1, −1, ±1) aimed at the object-frame origin."""
  sources = np.array([[1, -1, 1], [-1, -1, 1], [1, -1, -1], [-1, -1, -1]], np.float32)
  return Pushes(sources=sources, targets=np.zeros_like(sources),
                magnitudes=np.full(4, magnitude, np.float32), duration=1)


def push_points(prims: Primitives, pushes: Pushes) -> jax.Array:
  """(P, 3) object-frame points where each push acts on one object (K slots)."""
  def one(source, target):
    direction = (target - source) / jnp.linalg.norm(target - source)
    t = ray_box_hits(source, direction, prims).min()
    return jnp.where(jnp.isfinite(t), source + jnp.where(jnp.isfinite(t), t, 0.0) * direction,
                     target)
  return jax.vmap(one)(jnp.asarray(pushes.sources), jnp.asarray(pushes.targets))


def push_wrenches(prims: Primitives, pushes: Pushes,
                  props: MassProperties | None = None) -> jax.Array:
  """(P, 6) world force and torque about the centre of mass at rest, for one object."""
  props = mass_properties(prims) if props is None else props
  sources, targets = jnp.asarray(pushes.sources), jnp.asarray(pushes.targets)
  direction = (targets - sources) / jnp.linalg.norm(targets - sources, axis=-1, keepdims=True)
  force = direction * jnp.asarray(pushes.magnitudes)[:, None]
  torque = jnp.cross(push_points(prims, pushes) - props.com, force)
  return jnp.concatenate([force, torque], -1)
