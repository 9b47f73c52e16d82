"""Physical primitives (oriented boxes with densities) and their geometry in JAX."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ppdjax.conventions import NUM_SLOTS, ORDER_LEVEL

QUAT_TOL = 1e-3  # allowed | |q| - 1 | for a "unit" quaternion


@struct.dataclass
class Primitives:
  """A set of oriented boxes in the object frame; batches add leading axes.

  Attributes:
    half_size: (..., K, 3) half extents in metres, in [0, 0.5].
    pos: (..., K, 3) box centres in the object frame, in [-0.5, 0.5].
    quat: (..., K, 4) orientations (w, x, y, z), unit norm.
    density: (..., K) kg/m^3 (a block's mean density where it is not uniform).
    valid: (..., K) bool; padded slots are False and take no part in anything.
    inertia_scale: None (every box of one material throughout: the model's boxes, the
      paper's towers), or (..., K) > 0: each box's inertia about its centre over that of a
      uniform box of its mean density (a hollow shell: above 1; `dataset.hollow`). Only the
      simulator reads it (`sim.mass.mass_properties`).
  """

  half_size: jax.Array
  pos: jax.Array
  quat: jax.Array
  density: jax.Array
  valid: jax.Array
  inertia_scale: jax.Array | None = None

  @property
  def batch_shape(self) -> tuple[int, ...]:
    return tuple(np.shape(self.density)[:-1])

  @property
  def num_slots(self) -> int:
    return int(np.shape(self.density)[-1])

  def validate(self) -> "Primitives":
    """Checks shapes and values on concrete arrays; raises ValueError naming the field.

    Returns:
      self, so that `prims = prims.validate()` reads naturally.
    """
    validate(self)
    return self


# Every object's fields, in the constructor's order (`inertia_scale`, optional, apart).
FIELDS = tuple(f.name for f in dataclasses.fields(Primitives))[:5]  # half_size ... valid


def flatten(prims: Primitives) -> tuple[Primitives, tuple[int, ...]]:
  """(Primitives (N, K), batch shape B...) of Primitives (B..., K); undo with `unflatten`."""
  batch = prims.batch_shape
  return jax.tree.map(lambda x: x.reshape((-1,) + np.shape(x)[len(batch):]), prims), batch


def unflatten(x, batch: tuple[int, ...]):
  """Arrays (or a pytree of them) with a leading (N,) axis back to (B..., ...)."""
  return jax.tree.map(lambda a: a.reshape(tuple(batch) + a.shape[1:]), x)


def stack(prims: list[Primitives]) -> Primitives:
  """Stacks one-object Primitives (NumPy) on a new leading axis (`inertia_scale` where any
  has one: 1 for the others)."""
  out = Primitives(*[np.stack([np.asarray(getattr(p, f)) for p in prims]) for f in FIELDS])
  if all(p.inertia_scale is None for p in prims):
    return out
  return out.replace(inertia_scale=np.stack([
      np.ones(p.num_slots, np.float32) if p.inertia_scale is None
      else np.asarray(p.inertia_scale, np.float32) for p in prims]))


def _fail(field: str, problem: str):
  raise ValueError(f"Primitives.{field}: {problem}")


def validate(prims: Primitives) -> None:
  """Raises ValueError (naming the field) unless `prims` is a well-formed batch of boxes."""
  try:
    arrays = {k: np.asarray(getattr(prims, k)) for k in FIELDS}
    scale = None if prims.inertia_scale is None else np.asarray(prims.inertia_scale)
  except jax.errors.TracerArrayConversionError as e:
    raise ValueError("Primitives.validate() needs concrete arrays; call it outside jit") from e
  density = arrays["density"]
  if density.ndim < 1:
    _fail("density", f"expected shape (..., K), got {density.shape}")
  lead = density.shape
  expected = {"half_size": lead + (3,), "pos": lead + (3,), "quat": lead + (4,),
              "density": lead, "valid": lead}
  for name, shape in expected.items():
    if arrays[name].shape != shape:
      _fail(name, f"expected shape {shape} (batch + (K,) from density), got {arrays[name].shape}")
  for name in FIELDS[:-1]:  # the floating fields; `valid` is bool
    a = arrays[name]
    if not np.issubdtype(a.dtype, np.floating):
      _fail(name, f"expected a floating dtype, got {a.dtype}")
    if not np.all(np.isfinite(a)):
      _fail(name, "contains NaN or inf")
  if arrays["valid"].dtype != np.bool_:
    _fail("valid", f"expected dtype bool, got {arrays['valid'].dtype}")
  valid = arrays["valid"]
  if np.any(arrays["half_size"] < 0):
    _fail("half_size", "negative half size")
  if np.any(valid[..., None] & (arrays["half_size"] <= 0)):
    _fail("half_size", "a valid box has a zero half size")
  norm = np.linalg.norm(arrays["quat"], axis=-1)
  if np.any(np.abs(norm - 1) > QUAT_TOL):
    _fail("quat", f"not unit norm (|q| ranges {norm.min():.4g}..{norm.max():.4g})")
  if np.any(valid & (density <= 0)):
    _fail("density", "a valid box has a non-positive density")
  if scale is not None:
    if scale.shape != lead:
      _fail("inertia_scale", f"expected shape {lead} (batch + (K,) from density), got "
            f"{scale.shape}")
    if not np.issubdtype(scale.dtype, np.floating) or not np.all(np.isfinite(scale)):
      _fail("inertia_scale", "expected finite floats")
    if np.any(valid & (scale <= 0)):
      _fail("inertia_scale", "a valid box has a non-positive inertia scale")
  if np.any(~valid.any(axis=-1)):
    _fail("valid", "an object has no valid box")


def check(prims, name: str = "prims") -> None:
  """The public functions' check of their boxes: TypeError unless `prims` is a Primitives;
  `validate` where its arrays are concrete (traced ones are the jitted caller's contract)."""
  if not isinstance(prims, Primitives):
    raise TypeError(f"{name}: expected ppdjax.Primitives, got {type(prims).__name__}")
  if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(prims)):
    validate(prims)


def make(half_size, pos, quat=None, density=1000.0, num_slots: int = NUM_SLOTS) -> Primitives:
  """Builds padded Primitives from n <= num_slots boxes (numpy/list inputs, one object).

  Args:
    half_size: (n, 3).
    pos: (n, 3).
    quat: (n, 4) or None for identity.
    density: scalar or (n,).
    num_slots: K, the padded count.

  Raises ValueError naming the field for boxes `validate` refuses (a negative half size, a
  quaternion that is not unit, a density <= 0, NaN).
  """
  half_size = np.asarray(half_size, np.float32).reshape(-1, 3)
  n = half_size.shape[0]
  if n > num_slots:
    raise ValueError(f"{n} boxes do not fit in {num_slots} slots")
  pos = np.asarray(pos, np.float32).reshape(n, 3)
  quat = (np.tile([1.0, 0, 0, 0], (n, 1)) if quat is None else np.asarray(quat)).astype(np.float32)
  density = np.broadcast_to(np.asarray(density, np.float32), (n,))
  pad = num_slots - n
  return Primitives(
      half_size=np.concatenate([half_size, np.zeros((pad, 3), np.float32)]),
      pos=np.concatenate([pos, np.zeros((pad, 3), np.float32)]),
      quat=np.concatenate([quat.reshape(n, 4), np.tile(np.float32([1, 0, 0, 0]), (pad, 1))]),
      density=np.concatenate([density, np.zeros(pad, np.float32)]),
      valid=np.arange(num_slots) < n,
  ).validate()


# --- quaternion helpers (w, x, y, z) -----------------------------------------------------


def array_module(*arrays):
  """NumPy for NumPy inputs (arrays or scalars: no device round trip, for host code such
  as the tower generator that calls these once per tower), jax.numpy otherwise."""
  return np if all(isinstance(a, np.ndarray | np.generic) for a in arrays) else jnp


def quat_to_mat(q: jax.Array) -> jax.Array:
  """(..., 4) unit quaternions -> (..., 3, 3) rotation matrices (columns = body axes);
  NumPy in, NumPy out."""
  xp = array_module(q)
  w, x, y, z = xp.moveaxis(q, -1, 0)
  return xp.stack([
      xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
      xp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
      xp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
  ], -2)


def mat_to_quat(r: jax.Array) -> jax.Array:
  """(3, 3) rotation matrix -> (4,) unit quaternion with w >= 0 (Shepperd's method)."""
  tr = jnp.trace(r)
  cands = jnp.stack([
      jnp.array([1 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]),
      jnp.array([r[2, 1] - r[1, 2], 1 + 2 * r[0, 0] - tr, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]]),
      jnp.array([r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1 + 2 * r[1, 1] - tr, r[1, 2] + r[2, 1]]),
      jnp.array([r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1 + 2 * r[2, 2] - tr]),
  ])
  pick = jnp.argmax(jnp.array([tr, r[0, 0], r[1, 1], r[2, 2]]))
  q = cands[pick]
  q = q / jnp.linalg.norm(q)
  return q * jnp.where(q[0] < 0, -1.0, 1.0)


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
  """Hamilton product a ⊗ b of (..., 4) quaternions."""
  aw, ax, ay, az = jnp.moveaxis(a, -1, 0)
  bw, bx, by, bz = jnp.moveaxis(b, -1, 0)
  return jnp.stack([
      aw * bw - ax * bx - ay * by - az * bz,
      aw * bx + ax * bw + ay * bz - az * by,
      aw * by - ax * bz + ay * bw + az * bx,
      aw * bz + ax * by - ay * bx + az * bw,
  ], -1)


# --- box geometry ---------------------------------------------------------------------------

_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                         np.float32)


def corners(prims: Primitives) -> jax.Array:
  """(..., K, 8, 3) box corners in the object frame; NumPy in, NumPy out."""
  xp = array_module(prims.half_size, prims.pos, prims.quat)
  local = _CORNER_SIGNS * prims.half_size[..., None, :]
  rot = quat_to_mat(prims.quat)
  return xp.einsum("...ij,...cj->...ci", rot, local) + prims.pos[..., None, :]


def lowest_point(prims: Primitives) -> jax.Array:
  """(...,) lowest z over the corners of valid boxes, in the object frame; NumPy in, NumPy
  out."""
  xp = array_module(prims.half_size, prims.pos, prims.quat, prims.valid)
  z = corners(prims)[..., 2].min(axis=-1)
  return xp.where(prims.valid, z, xp.inf).min(axis=-1)


def ray_box_hits(origin: jax.Array, direction: jax.Array, prims: Primitives) -> jax.Array:
  """Distance along a ray to each box (slab method); inf where the ray misses.

  Args:
    origin: (3,) ray origin in the object frame.
    direction: (3,) unit direction.
    prims: one object, (K, ...) fields.

  Returns:
    (K,) the ray parameter t >= 0 of the first hit per box (0 if the origin is inside),
    inf for misses and invalid boxes.
  """
  rot = quat_to_mat(prims.quat)  # (K, 3, 3)
  o = jnp.einsum("kji,kj->ki", rot, origin - prims.pos)  # R^T (o - p)
  d = jnp.einsum("kji,j->ki", rot, direction)
  tiny = 1e-12
  safe_d = jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d)
  t1 = (-prims.half_size - o) / safe_d
  t2 = (prims.half_size - o) / safe_d
  t_near = jnp.minimum(t1, t2).max(axis=-1)
  t_far = jnp.maximum(t1, t2).min(axis=-1)
  hit = (t_far >= jnp.maximum(t_near, 0.0)) & prims.valid
  return jnp.where(hit, jnp.maximum(t_near, 0.0), jnp.inf)


# --- bottom-to-top order: how the generator, its targets and every metric list boxes ------


def bottom_to_top_order(prims: Primitives) -> jax.Array:
  """(..., K) box indices bottom to top, padding last: by level, then by centre x.

  Levels: boxes sorted by centre height, a new level wherever the next centre is more than
  `ORDER_LEVEL` (one voxel) higher. A tower's blocks each get their own level (the order
  is by height); the parts of a tool lying flat share one and go from -x to +x, an order
  the voxels show where sub-voxel height differences would not. Stable for exact ties.
  NumPy in, NumPy out (the evaluation's reading thread calls it per batch).
  """
  xp = array_module(prims.pos, prims.valid)
  z = xp.where(prims.valid, prims.pos[..., 2], xp.inf)
  by_z = xp.argsort(z, axis=-1, stable=True)
  z_sorted = xp.take_along_axis(z, by_z, axis=-1)
  with np.errstate(invalid="ignore"):  # inf - inf is nan: no step
    steps = xp.diff(z_sorted, axis=-1) > ORDER_LEVEL
  level_sorted = xp.concatenate(
      [xp.zeros_like(steps[..., :1], xp.int32), xp.cumsum(steps, -1, dtype=xp.int32)], -1)
  level = xp.take_along_axis(level_sorted, xp.argsort(by_z, axis=-1), axis=-1)
  level = xp.where(prims.valid, level, xp.iinfo(xp.int32).max)
  by_x = xp.argsort(xp.where(prims.valid, prims.pos[..., 0], xp.inf), axis=-1, stable=True)
  then_level = xp.argsort(xp.take_along_axis(level, by_x, axis=-1), axis=-1, stable=True)
  return xp.take_along_axis(by_x, then_level, axis=-1).astype(xp.int32)


def bottom_to_top(prims: Primitives) -> Primitives:
  """Each object's boxes reordered bottom to top (`bottom_to_top_order`); padding last."""
  order = bottom_to_top_order(prims)
  return jax.tree.map(lambda x: jnp.take_along_axis(
      jnp.asarray(x), order.reshape(order.shape + (1,) * (jnp.ndim(x) - order.ndim)),
      axis=order.ndim - 1), prims)


# --- one label per box ---------------------------------------------------------------------


def _box_symmetries() -> np.ndarray:
  """(48, 4) the quaternions of the cube's 24 rotations, each with both signs."""
  qs = []
  for i in range(4):
    for s in (1, -1):
      q = np.zeros(4)
      q[i] = s
      qs.append(q)
  for signs in np.ndindex(2, 2, 2, 2):
    qs.append(0.5 * (1 - 2 * np.array(signs)))
  for i in range(4):
    for j in range(i + 1, 4):
      for si in (1, -1):
        for sj in (1, -1):
          q = np.zeros(4)
          q[i], q[j] = si / np.sqrt(2), sj / np.sqrt(2)
          qs.append(q)
  return np.array(qs, np.float32)


BOX_SYMMETRIES = _box_symmetries()


def canonical_boxes(prims: Primitives) -> Primitives:
  """One label per box: the rotation nearest the identity, with w >= 0.

  A box (s, q) is the same solid as (|G|ᵀ s, q ⊗ g) for each of the cube's 24 rotations
  g (matrix G), and as (s, −q). Of these 48 labels this picks the one whose quaternion
  has the largest w, i.e. the smallest rotation angle (ties, a measure-zero set such as
  exact 45° turns, go to the first in a fixed order); w >= 0 follows. An axis-aligned
  box therefore keeps q = (1, 0, 0, 0) and its half sizes along x, y, z.
  """
  g = jnp.asarray(BOX_SYMMETRIES)  # (48, 4)
  cand = quat_mul(prims.quat[..., None, :], g)  # (..., K, 48, 4)
  best = jnp.argmax(cand[..., 0], axis=-1)  # (..., K)
  quat = jnp.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
  perm = jnp.abs(quat_to_mat(g))[best]  # (..., K, 3, 3) |G|
  half_size = jnp.einsum("...ji,...j->...i", perm, prims.half_size)
  return prims.replace(half_size=half_size, quat=quat)
