"""RGB (and GL depth) images of an object at rest, with MuJoCo's renderer (MUJOCO_GL=egl).

One render model holds K textured box slots; per object the boxes' geometry, rest pose and
texture pixels are written into it and the textures re-uploaded, so a single GL context
renders a whole dataset. Camera and light are fixed: the camera (`dataset.camera`) looks at
the object's middle from the front-right (+x, -y) and above. The dataset's depth images
come from the exact ray cast (`dataset.depth`); MuJoCo's GL depth pass stays available
(`depth=True`) as an independent check of it.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from ppdjax.conventions import NUM_SLOTS  # noqa: E402
from ppdjax.dataset import camera, materials  # noqa: E402
from ppdjax.primitives import Primitives  # noqa: E402
from ppdjax.sim import scene  # noqa: E402

HIDDEN_GROUP = 3  # geom group not drawn by default: padded slots go there


def _camera_xyaxes() -> str:
  right, up, _ = camera.camera_axes()
  return " ".join(f"{v:.6f}" for v in np.concatenate([right, up]))


def box_geoms(num_slots: int = NUM_SLOTS) -> str:
  """MJCF of the K textured box geoms box{k} (material mat{k}), written per object."""
  # generic placeholder poses: MuJoCo skips the transform of a geom it compiled as sitting
  # at the body frame (geom_sameframe), which would ignore the poses written per object
  return "\n".join(
      f'      <geom name="box{k}" type="box" size="0.1 0.1 0.1" material="mat{k}" '
      f'pos="{0.01 * (k + 1)} 0.02 0.03" quat="0.9 0.1 0.2 0.3"/>' for k in range(num_slots))


def render_xml(num_slots: int = NUM_SLOTS, texture_size: int = materials.TEXTURE_SIZE) -> str:
  return stage_xml(material_assets(num_slots, texture_size), box_geoms(num_slots))


def material_assets(count: int, texture_size: int = materials.TEXTURE_SIZE) -> str:
  """MJCF assets tex{k} / mat{k}, k < count: flat placeholder textures whose pixels are
  written per object (`write_texture`)."""
  return "\n".join(
      f'    <texture name="tex{k}" type="2d" builtin="flat" width="{texture_size}" '
      f'height="{texture_size}" rgb1="1 1 1"/>\n'
      f'    <material name="mat{k}" texture="tex{k}" texuniform="true" texrepeat="4 4" '
      f'specular="0.3" shininess="0.3"/>' for k in range(count))


def write_texture(model, tex: int, material: str, seed: int) -> None:
  """Writes a material's procedural texture (`materials.texture`) into texture `tex`."""
  size = model.tex_width[tex] * model.tex_height[tex] * model.tex_nchannel[tex]
  img = materials.texture(material, seed, int(model.tex_width[tex]))
  model.tex_data[model.tex_adr[tex]:model.tex_adr[tex] + size] = img.reshape(-1)


def stage_xml(assets: str, object_geoms: str, extra_assets: str = "") -> str:
  """The rendered scene (floor, sky, light, the camera `view`) around an object body."""
  pos = " ".join(f"{v}" for v in camera.CAMERA_POS)
  light = " ".join(f"{v}" for v in camera.LIGHT_DIR)
  return f"""<mujoco model="ppdjax_render">
  <visual><global offwidth="1024" offheight="1024"/><quality shadowsize="2048"/></visual>
  <asset>
    <texture name="floor" type="2d" builtin="checker" width="256" height="256"
             rgb1="0.82 0.82 0.80" rgb2="0.68 0.68 0.66"/>
    <material name="floor" texture="floor" texrepeat="8 8"/>
    <texture type="skybox" builtin="gradient" rgb1="0.75 0.82 0.9" rgb2="0.95 0.95 0.95"
             width="64" height="64"/>
{assets}
{extra_assets}
  </asset>
  <worldbody>
    <light pos="2 -1 4" dir="{light}" directional="true" diffuse="0.8 0.8 0.8"/>
    <camera name="view" pos="{pos}" xyaxes="{_camera_xyaxes()}" fovy="{camera.FOVY}"/>
    <geom name="ground" type="plane" size="5 5 0.1" material="floor"/>
    <body name="object" pos="0 0 0.5">
{object_geoms}
    </body>
  </worldbody>
</mujoco>"""


def open_renderer(model, height: int, width: int):
  """mujoco.Renderer, or a RuntimeError that says how to get headless OpenGL."""
  try:
    return mujoco.Renderer(model, height, width)
  except Exception as e:  # no usable OpenGL: say how to get one
    raise RuntimeError(
        "MuJoCo could not open a headless OpenGL context (MUJOCO_GL="
        f"{os.environ.get('MUJOCO_GL')}). Set MUJOCO_GL=egl before mujoco is first "
        "imported, and install EGL (Debian: libegl1 libgl1-mesa-dri), or use "
        "MUJOCO_GL=osmesa with libosmesa6.") from e


def write_boxes(model, first_geom: int, prims: Primitives) -> None:
  """Writes one object's K boxes (numpy or JAX fields) into the render model's K box
  geoms from `first_geom` on; padded slots go to the hidden group."""
  p = jax.tree.map(np.asarray, prims)
  valid = p.valid.astype(bool)
  g = slice(first_geom, first_geom + len(valid))
  model.geom_size[g] = np.where(valid[:, None], p.half_size, 0.01)
  model.geom_pos[g] = p.pos
  model.geom_quat[g] = p.quat / np.linalg.norm(p.quat, axis=-1, keepdims=True)
  model.geom_rbound[g] = np.linalg.norm(model.geom_size[g], axis=-1)
  model.geom_group[g] = np.where(valid, 0, HIDDEN_GROUP)


def upload_textures(model, renderer, tex_ids, valid, material_ids, texture_seeds) -> None:
  """Writes each valid slot's texture and uploads it to the renderer's GL context;
  `material_ids` index `materials.LOOK_NAMES` (a material's id is its own texture's)."""
  renderer._gl_context.make_current()  # pylint: disable=protected-access
  for slot in np.flatnonzero(valid):
    write_texture(model, tex_ids[slot], materials.LOOK_NAMES[int(material_ids[slot])],
                  int(texture_seeds[slot]))
    mujoco.mjr_uploadTexture(model, renderer._mjr_context, tex_ids[slot])  # pylint: disable=protected-access


class SlotRenderer:
  """A render model with K textured box slots (box{k}, tex{k}) and its GL renderer; a
  context manager. Subclasses say what the scene holds and how it is drawn."""

  def __init__(self, xml: str, height: int, width: int, num_slots: int):
    self.model = mujoco.MjModel.from_xml_string(xml)
    # the offscreen buffer the scene declares bounds the frame
    high, wide = self.model.vis.global_.offheight, self.model.vis.global_.offwidth
    if not (16 <= height <= high and 16 <= width <= wide):
      raise ValueError(f"image size must be within 16..{high} x 16..{wide} pixels, got "
                       f"{height}x{width}")
    self.data = mujoco.MjData(self.model)
    self._renderer = open_renderer(self.model, height, width)
    self._first_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "box0")
    self._tex_ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_TEXTURE, f"tex{k}")
                     for k in range(num_slots)]
    self.num_slots = num_slots

  def write_object(self, prims: Primitives, material_ids, texture_seeds) -> None:
    """Writes one object's boxes and uploads its slots' textures."""
    write_boxes(self.model, self._first_geom, prims)
    upload_textures(self.model, self._renderer, self._tex_ids,
                    np.asarray(prims.valid).astype(bool), material_ids, texture_seeds)

  def close(self):
    self._renderer.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()


class ObjectRenderer(SlotRenderer):
  """Renders objects (K slots) with per-block material textures; reuse it for many objects.

  Args:
    height, width: image size in pixels.
    num_slots: K.
  """

  def __init__(self, height: int = 224, width: int = 224, num_slots: int = NUM_SLOTS):
    super().__init__(render_xml(num_slots), height, width, num_slots)

  def render(self, prims: Primitives, material_ids, texture_seeds, depth: bool = True
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """RGB (H, W, 3) uint8 and MuJoCo's depth (H, W) float32 metres (None without `depth`)
    of one object at rest.

    Args:
      prims: one object (K slots).
      material_ids: (K,) texture per slot (`materials.LOOK_NAMES`: a material's id shows
        its own texture; ignored for invalid slots).
      texture_seeds: (K,) texture seed per slot.
    """
    m = self.model
    self.write_object(prims, material_ids, texture_seeds)
    m.body_pos[1] = scene.rest_position(jax.tree.map(np.asarray, prims))
    mujoco.mj_forward(m, self.data)
    self._renderer.update_scene(self.data, camera="view")
    rgb = self._renderer.render().copy()
    if not depth:
      return rgb, None
    # A second pass for depth: MuJoCo's depth-only pass (no skybox: the sky reads as the
    # far plane) rather than the colour pass's depth buffer, whose values differ.
    self._renderer.enable_depth_rendering()
    self._renderer.update_scene(self.data, camera="view")
    depth = self._renderer.render().astype(np.float32)
    self._renderer.disable_depth_rendering()
    return rgb, depth


_WORKER = {}


def _worker_init(height, width, num_slots):
  _WORKER["renderer"] = ObjectRenderer(height, width, num_slots)


def _worker_render(args):
  prims, material_ids, seeds, depth = args
  r = _WORKER["renderer"]
  out = [r.render(jax.tree.map(lambda x, i=i: x[i], prims), material_ids[i], seeds[i], depth)
         for i in range(len(material_ids))]
  return (np.stack([o[0] for o in out]),
          np.stack([o[1] for o in out]) if depth else None)


def cpu_process_pool(workers: int, initializer=None, initargs=()):
  """A pool of `workers` spawned processes (JAX and GL contexts do not survive a fork)
  whose JAX stays on the CPU: they use it for a little geometry, and the accelerator's
  memory belongs to the parent."""
  import multiprocessing  # pylint: disable=import-outside-toplevel
  saved = os.environ.get("JAX_PLATFORMS")
  os.environ["JAX_PLATFORMS"] = "cpu"
  try:
    return multiprocessing.get_context("spawn").Pool(workers, initializer, initargs)
  finally:
    if saved is None:
      os.environ.pop("JAX_PLATFORMS")
    else:
      os.environ["JAX_PLATFORMS"] = saved


class BatchRenderer:
  """Renders batches of objects, in `workers` processes (each with its own GL context).

  workers=0 renders in this process. Results do not depend on the number of workers.
  With depth=False, `render` skips MuJoCo's depth pass and returns None for it.
  """

  def __init__(self, height: int = 224, width: int = 224, workers: int = 0,
               num_slots: int = NUM_SLOTS, depth: bool = True):
    self.workers, self.depth = workers, depth
    if workers > 0:
      self._pool = cpu_process_pool(workers, _worker_init, (height, width, num_slots))
    else:
      _worker_init(height, width, num_slots)
      self._pool = None

  def render(self, prims: Primitives, material_ids, seeds):
    """(N, H, W, 3) uint8 and (N, H, W) float32 (or None) for a batch of N objects."""
    p = jax.tree.map(np.asarray, prims)
    n = len(material_ids)
    if self._pool is None:
      return _worker_render((p, material_ids, seeds, self.depth))
    chunks = np.array_split(np.arange(n), min(n, self.workers * 4))
    parts = self._pool.map(_worker_render, [
        (jax.tree.map(lambda x, c=c: x[c], p), material_ids[c], seeds[c], self.depth)
        for c in chunks])
    return (np.concatenate([a for a, _ in parts]),
            np.concatenate([b for _, b in parts]) if self.depth else None)

  def close(self):
    if self._pool is not None:
      self._pool.close()
      self._pool.join()
    elif "renderer" in _WORKER:
      _WORKER.pop("renderer").close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()
