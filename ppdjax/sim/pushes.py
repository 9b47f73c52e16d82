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

from ppdjax.conventions import PUSH_MAGNITUDES, TIMESTEP
from ppdjax.primitives import Primitives, ray_box_hits
from ppdjax.sim.mass import MassProperties, mass_properties

PAPER_FORCE = 1e5  # N, applied for one step of 1/300 s (impulse ~333 N s)

# The pendulum of the paper's real towers (Sec. 5.3), scaled to 1 m objects (docs/physics.md
# "Strikes"): a copper ball of radius 20 cm (300 kg) on a 2 m string released at 70 degrees
# hits the tower horizontally (from -y) at 5.1 m/s, 10 cm above the object-frame origin.
COPPER_DENSITY = 8960.0  # kg/m^3
BALL_RADIUS = 0.2  # m
PENDULUM_LENGTH = 2.0  # m, pivot to ball centre
RELEASE_ANGLE = 70.0  # degrees from the vertical
STRIKE_HEIGHT = 0.1  # m above the object-frame origin
RESTITUTION = 0.5  # copper on wood or metal (Newton's coefficient)


@struct.dataclass
class Pushes:
  """P pushes, each a force of `magnitude` from `source` towards `target` (object frame).

  Attributes:
    sources: (P, 3) metres, relative to the object-frame origin at rest.
    targets: (P, 3) metres, same frame.
    magnitudes: (P,) newtons; for a strike, the striker's speed at impact (m/s).
    duration: steps during which each force acts (static).
    striker_masses: None (plain pushes), or (P,) kg: each push is a strike.
    restitution: Newton's coefficient of a strike, in [0, 1] (static).
  """

  sources: jax.Array
  targets: jax.Array
  magnitudes: jax.Array
  duration: int = struct.field(pytree_node=False, default=1)
  striker_masses: jax.Array | None = None
  restitution: float = struct.field(pytree_node=False, default=RESTITUTION)

  @property
  def num(self) -> int:
    return int(np.shape(self.magnitudes)[0])

  @property
  def is_strike(self) -> bool:
    return self.striker_masses is not None

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
    if self.is_strike:
      strikers = np.asarray(self.striker_masses)
      if strikers.shape != (p,):
        raise ValueError(f"Pushes.striker_masses: expected shape ({p},), got {strikers.shape}")
      if not np.all(np.isfinite(strikers)) or np.any(strikers <= 0):
        raise ValueError("Pushes.striker_masses: expected finite masses > 0 kg")
      if not 0.0 <= float(self.restitution) <= 1.0:
        raise ValueError(f"Pushes.restitution: expected a value in [0, 1], got "
                         f"{self.restitution!r}")
    return self

  def arrays(self) -> tuple:
    """(sources, targets, magnitudes, striker_masses or None) as float32 arrays."""
    f32 = lambda x: None if x is None else jnp.asarray(x, jnp.float32)  # noqa: E731
    return (f32(self.sources), f32(self.targets), f32(self.magnitudes),
            f32(self.striker_masses))

  def float32(self) -> "Pushes":
    """The same pushes with float32 JAX arrays (what the jitted rollouts take)."""
    sources, targets, magnitudes, striker_masses = self.arrays()
    return self.replace(sources=sources, targets=targets, magnitudes=magnitudes,
                        striker_masses=striker_masses)


def object_magnitudes(pushes: Pushes, observation: dict, count: int) -> jax.Array:
  """(count, P) float32: each object's push magnitudes, observation["push_magnitudes"]
  where given (`conventions.PUSH_MAGNITUDES`), else the pushes' own for every object."""
  given = observation.get(PUSH_MAGNITUDES)
  if given is not None:
    return jnp.asarray(given, jnp.float32).reshape(count, pushes.num)
  return jnp.broadcast_to(jnp.asarray(pushes.magnitudes, jnp.float32), (count, pushes.num))


def check_magnitudes(magnitudes, pushes: Pushes, lead: tuple[int, ...]) -> None:
  """Raises ValueError naming the problem with per-object push magnitudes (newtons): shape
  lead + (P,), finite, >= 0."""
  got = tuple(np.shape(magnitudes))
  if got != tuple(lead) + (pushes.num,):
    raise ValueError(f"observation[{PUSH_MAGNITUDES!r}]: expected shape "
                     f"{tuple(lead) + (pushes.num,)} (newtons per push), got {got}")
  if not isinstance(magnitudes, jax.core.Tracer):
    m = np.asarray(magnitudes, np.float64)
    if not np.all(np.isfinite(m)) or np.any(m < 0):
      raise ValueError(f"observation[{PUSH_MAGNITUDES!r}]: expected finite magnitudes >= 0 N")


def default_pushes(magnitude: float = PAPER_FORCE) -> Pushes:
  """The paper's four pushes: sources (±1, −1, ±1) aimed at the object-frame origin."""
  sources = np.array([[1, -1, 1], [-1, -1, 1], [1, -1, -1], [-1, -1, -1]], np.float32)
  return Pushes(sources=sources, targets=np.zeros_like(sources),
                magnitudes=np.full(4, magnitude, np.float32), duration=1)


def pendulum_strike(*, height: float = STRIKE_HEIGHT, ball_radius: float = BALL_RADIUS,
                    length: float = PENDULUM_LENGTH, release_deg: float = RELEASE_ANGLE,
                    restitution: float = RESTITUTION) -> Pushes:
  """One strike of a copper ball on a pendulum (the paper's real setup, Sec. 5.3).

  The ball, released from rest at `release_deg` from the vertical, reaches the bottom of
  its swing at sqrt(2 g L (1 - cos angle)) (5.1 m/s by default) and hits the object there,
  horizontally along +y, `height` above the object-frame origin.
  """
  speed = np.sqrt(2 * 9.81 * length * (1 - np.cos(np.deg2rad(release_deg))))
  mass = COPPER_DENSITY * 4 / 3 * np.pi * ball_radius ** 3
  return Pushes(sources=np.array([[0.0, -1.0, height]], np.float32),
                targets=np.array([[0.0, 0.0, height]], np.float32),
                magnitudes=np.array([speed], np.float32), duration=1,
                striker_masses=np.array([mass], np.float32),
                restitution=float(restitution)).validate()


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
  direction = _directions(pushes)
  if pushes.is_strike:
    magnitude = strike_impulses(prims, pushes, props) / (pushes.duration * TIMESTEP)
  else:
    magnitude = jnp.asarray(pushes.magnitudes)
  force = direction * magnitude[:, None]
  torque = jnp.cross(push_points(prims, pushes) - props.com, force)
  return jnp.concatenate([force, torque], -1)


def _directions(pushes: Pushes) -> jax.Array:
  sources, targets = jnp.asarray(pushes.sources), jnp.asarray(pushes.targets)
  return (targets - sources) / jnp.linalg.norm(targets - sources, axis=-1, keepdims=True)


def strike_impulses(prims: Primitives, pushes: Pushes,
                    props: MassProperties | None = None) -> jax.Array:
  """(P,) N s: the impulse each strike gives one resting object (differentiable).

  A ball of mass m_s at speed v hits the object, free and at rest, at point r (from the
  centre of mass) along n. The object's mass seen at that point along n is m_eff, with
  1 / m_eff = 1 / m + (r x n) . I^-1 (r x n); Newton's restitution e gives the impulse
  J = (1 + e) v / (1 / m_s + 1 / m_eff). The ground's reaction during the strike is left
  to the simulator's first step, where the impulse acts as a force.
  """
  props = mass_properties(prims) if props is None else props
  n = _directions(pushes)
  r_x_n = jnp.cross(push_points(prims, pushes) - props.com, n)
  inv_inertia_r_x_n = jnp.linalg.solve(props.inertia, r_x_n.T).T
  inv_eff = 1.0 / props.mass + jnp.sum(r_x_n * inv_inertia_r_x_n, -1)
  inv_striker = 1.0 / jnp.asarray(pushes.striker_masses)
  return (1.0 + pushes.restitution) * jnp.asarray(pushes.magnitudes) / (inv_striker + inv_eff)
