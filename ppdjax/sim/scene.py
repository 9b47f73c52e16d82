"""The simulated scene: a template MuJoCo model and the per-object fields written into it.

One template serves every object: a ground plane and one free body holding K box geoms.
`object_fields` turns Primitives into the model fields that MuJoCo's compiler (and
mj_setConst) would have produced for that object, in pure JAX, so the MJX backend can
replace them inside jit and the C backend can write them into per-simulation models.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco

from ppdjax.conventions import NUM_SLOTS, REST_DEPTH, TIMESTEP
from ppdjax.primitives import Primitives, array_module, lowest_point, quat_to_mat
from ppdjax.sim import mass

OBJECT_BODY = 1  # body id of the object (0 is the world)
FIRST_BOX_GEOM = 1  # geom 0 is the ground plane


# The solver options of every simulated scene (towers, tools): MuJoCo's defaults otherwise.
OPTION_XML = f"""  <option timestep="{TIMESTEP!r}" integrator="Euler" cone="pyramidal" solver="Newton">
    <flag midphase="disable" eulerdamp="disable"/>
  </option>"""


def scene_xml(boxes: list[dict] | None = None, num_slots: int = NUM_SLOTS) -> str:
  """MJCF of the scene; `boxes` (size, pos, quat, density dicts) instead of placeholders
  makes a model MuJoCo's compiler sets up for one object (the tests' reference)."""
  if boxes is None:  # template: placeholder boxes, replaced per object
    # Generic poses, so the compiler marks no geom or inertial frame as coinciding with the
    # body frame (MuJoCo C skips those transforms, which would ignore the fields we write).
    boxes = [dict(size=(0.1 + 0.01 * i, 0.12, 0.08), pos=(0.01 * (i + 1), -0.02 * i, 0.03 * i),
                  quat=(0.9, 0.1 * (i + 1), 0.2, -0.1), density=1000.0)
             for i in range(num_slots)]
  geoms = "\n".join(
      f'      <geom name="box{i}" type="box" size="{_v(b["size"])}" pos="{_v(b["pos"])}" '
      f'quat="{_v(b["quat"])}" density="{b["density"]!r}"/>' for i, b in enumerate(boxes))
  return f"""<mujoco model="ppdjax_scene">
{OPTION_XML}
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
    <body name="object" pos="0 0 0.5">
      <freejoint name="object"/>
{geoms}
    </body>
  </worldbody>
</mujoco>"""


def _v(x) -> str:
  return " ".join(repr(float(v)) for v in x)


@functools.lru_cache(maxsize=4)
def template_model(num_slots: int = NUM_SLOTS) -> mujoco.MjModel:
  """The compiled template (MuJoCo's default solver settings; callers may copy and tune)."""
  return mujoco.MjModel.from_xml_string(scene_xml(num_slots=num_slots))


def rest_position(prims: Primitives) -> jax.Array:
  """(..., 3) world position of the object-frame origin at rest on the ground; NumPy in,
  NumPy out (the renderer calls it once per sample)."""
  z = -lowest_point(prims) - REST_DEPTH
  xp = array_module(z)
  return xp.stack([xp.zeros_like(z), xp.zeros_like(z), z], -1)


def object_fields(prims: Primitives) -> dict[str, jax.Array]:
  """Model fields for one object (K slots), as MuJoCo's compiler and mj_setConst set them.

  Invalid slots become a half-size copy of the first valid box, nested inside it: massless
  and never touching the ground while the valid box holds it up, so one compiled model
  serves objects of 1..K boxes.

  Returns:
    A dict of MjModel field name -> array with the template's shape.
  """
  first = jnp.argmax(prims.valid)
  v = prims.valid[:, None]
  half_size = jnp.where(v, prims.half_size, 0.5 * prims.half_size[first])
  geom_pos = jnp.where(v, prims.pos, prims.pos[first])
  geom_quat = jnp.where(v, prims.quat, prims.quat[first])
  geom_quat = geom_quat / jnp.linalg.norm(geom_quat, axis=-1, keepdims=True)

  props = mass.mass_properties(prims)
  moments, iquat = mass.principal_axes(props.inertia)
  inv_moments = 1.0 / moments
  # mj_setConst at qpos0 (identity orientation), free joint: A = J M^-1 J^T at the COM is
  # diag(1/m, I^-1), so body_invweight0 = (1/m, mean(1/moments)); the dof averages add the
  # lever arm of the COM for the translational dofs.
  c = props.com
  inertia_inv = jnp.einsum("ij,j,kj->ik", quat_to_mat(iquat), inv_moments, quat_to_mat(iquat))
  skew = jnp.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
  trans_block = jnp.eye(3) / props.mass + skew @ inertia_inv @ skew.T
  dof_inv = jnp.concatenate([jnp.full(3, jnp.trace(trans_block) / 3),
                             jnp.full(3, jnp.trace(inertia_inv) / 3)])
  zero2 = jnp.zeros((1,), props.mass.dtype)
  return {
      "geom_size": half_size,
      "geom_pos": geom_pos,
      "geom_quat": geom_quat,
      "geom_rbound": jnp.linalg.norm(half_size, axis=-1),
      "geom_aabb": jnp.concatenate([jnp.zeros_like(half_size), half_size], -1),
      "body_mass": jnp.concatenate([zero2, props.mass[None]]),
      "body_subtreemass": jnp.concatenate([props.mass[None], props.mass[None]]),
      "body_ipos": jnp.stack([jnp.zeros(3), c]),
      "body_iquat": jnp.stack([jnp.array([1.0, 0, 0, 0]), iquat]),
      "body_inertia": jnp.stack([jnp.zeros(3), moments]),
      "body_invweight0": jnp.stack([jnp.zeros(2), jnp.stack([1.0 / props.mass,
                                                             inv_moments.mean()])]),
      "dof_invweight0": dof_inv,
  }


# Fields that live on geoms 1..K of the template; the rest are full per-model arrays.
GEOM_FIELDS = ("geom_size", "geom_pos", "geom_quat", "geom_rbound", "geom_aabb")
