"""Independent references for the physics tests: models MuJoCo's compiler builds from boxes."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ppdjax.conventions import STEPS
from ppdjax.primitives import Primitives
from ppdjax.sim import scene
from ppdjax.sim.pushes import Pushes, push_wrenches


def reference_model(prims: Primitives) -> mujoco.MjModel:
  """A model compiled by MuJoCo from one object's valid boxes: the reference for tests."""
  p = jax.tree.map(np.asarray, prims)
  boxes = [dict(size=p.half_size[k], pos=p.pos[k], quat=p.quat[k], density=float(p.density[k]))
           for k in np.flatnonzero(p.valid)]
  return mujoco.MjModel.from_xml_string(scene.scene_xml(boxes))


def reference_rollout(prims: Primitives, pushes: Pushes, *, steps: int = STEPS) -> np.ndarray:
  """(P, steps, 7) for ONE object from a model MuJoCo compiled from its boxes and a plain
  mj_step loop: the independent reference the backends are tested against."""
  model = reference_model(prims)
  data = mujoco.MjData(model)
  wrenches = np.asarray(push_wrenches(jax.tree.map(jnp.asarray, prims), pushes), np.float64)
  rest = np.asarray(scene.rest_position(jax.tree.map(jnp.asarray, prims)), np.float64)
  out = np.zeros((pushes.num, steps, 7))
  for i in range(pushes.num):
    mujoco.mj_resetData(model, data)
    data.qpos[:3], data.qpos[3:7] = rest, [1, 0, 0, 0]
    for t in range(steps):
      data.xfrc_applied[scene.OBJECT_BODY] = wrenches[i] if t < pushes.duration else 0.0
      mujoco.mj_step(model, data)
      out[i, t] = data.qpos[:7]
  return out
