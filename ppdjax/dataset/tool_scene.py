"""A tool's own observations: trajectories simulated and an image rendered from its parts.

Inference explains a tool with boxes, but what it observes comes from the tool itself
(paper Sec. 5.2: the model mismatch is real):
- **Physics** (MuJoCo C): the tool is one free body on the ground plane, with the towers'
  solver options (`scene.OPTION_XML`). Its mass, centre of mass and inertia are the parts'
  exact ones (trimesh, each part's density; `mass_properties`). It collides through convex
  pieces: a part that is not convex (a bent handle) is cut into slabs along its longest
  axis, each slab's convex hull a mesh geom. Pushes follow the towers' convention
  (`ppdjax.sim.pushes`): a force from source to target at the first point where that ray
  meets the tool (here its convex pieces), applied for `duration` steps as force plus
  torque about the centre of mass; trajectories are the object-frame origin's pose.
- **Image**: the parts as meshes with their materials' textures (`materials.texture`),
  under the towers' camera and light (`render.render_xml`'s scene).
Both take a tool whose parts are in the normalised object frame (`meshes.normalize`).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ppdjax.conventions import REST_DEPTH, STEPS
from ppdjax.dataset.meshes import voxelize_parts
from ppdjax.sim import scene
from ppdjax.sim.pushes import Pushes, default_pushes

# The paper pushes tools as towers (1e5 N). Normalised to the unit cube, the tools here are
# thin and light (median 8 kg against about 100 kg for a tower): 1e5 N for a step would
# send them off at 100 m/s, and MuJoCo's solver diverges on 4 of 40 tools already at
# 1e4 N. 1e3 N moves the median tool 2.3 cm (p90 12 cm) in 256 steps, none diverging
# (docs/data.md); the directions are the paper's. At 1e3 N part of a tool's response to a
# small density change is a jump (rolling, tipping), not a trend; at 300 N it is
# proportional, at less than half the motion (experiments/results/tool_resolution/), yet
# between whole configurations 1e3 N tells densities apart as well
# (experiments/results/tool_push_study/).
# A dataset may choose another magnitude (`config.data.tool_push_force`).
TOOL_PUSH_FORCE = 1e3
PUSH_MODES = ("fixed", "by_volume")  # config.data.tool_push
# m^3: a normalised tool's volume (1 m long) about which "by_volume" pushes with the set
# force (the procedural tools' median is 0.0032, p1 0.0012, p99 0.021)
REFERENCE_VOLUME = 0.003
SLABS = 4  # convex pieces of a part that is not convex
CONVEX_TOL = 0.02  # a part whose hull exceeds its volume by this fraction is cut


def tool_pushes(force: float = TOOL_PUSH_FORCE) -> Pushes:
  """The paper's four push directions at the tools' magnitude (newtons; TOOL_PUSH_FORCE)."""
  return default_pushes(force)


def push_force_for(force: float, volume: float, mode: str) -> float:
  """The newtons a tool of `volume` m^3 (normalised, as its voxels show it) is pushed with:
  `force` ("fixed"), or `force` x volume / REFERENCE_VOLUME ("by_volume": a tool's mass is
  its volume times its mean density, so every tool of one mean density starts alike, and
  the motion reads the density; a fixed force moved the heaviest tools 1 cm/s while the
  lightest left at metres per second)."""
  if mode not in PUSH_MODES:
    raise ValueError(f"tool push mode must be one of {PUSH_MODES}, got {mode!r}")
  if not volume > 0:
    raise ValueError(f"a tool's volume must be > 0 m^3, got {volume!r}")
  return float(force) * (float(volume) / REFERENCE_VOLUME if mode == "by_volume" else 1.0)


def mass_properties(parts, densities) -> tuple[float, np.ndarray, np.ndarray]:
  """(mass kg, centre of mass (3,), inertia (3, 3) about it) of parts with densities."""
  masses, coms, inertias = [], [], []
  for part, rho in zip(parts, densities):
    part = part.copy()
    part.density = float(rho)
    masses.append(part.mass)
    coms.append(part.center_mass)
    inertias.append(part.moment_inertia)
  masses, coms = np.asarray(masses), np.asarray(coms)
  mass = masses.sum()
  com = (masses[:, None] * coms).sum(0) / mass
  inertia = np.zeros((3, 3))
  for m, c, i in zip(masses, coms, inertias):
    r = c - com
    inertia += i + m * (r @ r * np.eye(3) - np.outer(r, r))  # parallel axes
  return float(mass), com, inertia


def convex_pieces(part: trimesh.Trimesh) -> list[np.ndarray]:
  """Vertex sets whose convex hulls approximate the part: the part's own hull if it is
  (nearly) convex, else overlapping slabs along its longest axis."""
  v = np.asarray(part.vertices)
  if part.convex_hull.volume <= (1 + CONVEX_TOL) * abs(part.volume):
    return [v]
  axis = int(np.argmax(part.extents))
  lo, hi = v[:, axis].min(), v[:, axis].max()
  edges = np.linspace(lo, hi, SLABS + 1)
  margin = 0.05 * (hi - lo) / SLABS  # slabs overlap: no gap between neighbours' hulls
  pieces = [v[(v[:, axis] >= a - margin) & (v[:, axis] <= b + margin)]
            for a, b in zip(edges[:-1], edges[1:])]
  return [p for p in pieces if len(p) >= 4] or [v]


def rest_height(parts) -> float:
  """World z of the object-frame origin at rest: the lowest vertex on the ground."""
  return -min(float(p.vertices[:, 2].min()) for p in parts) - REST_DEPTH


def _floats(x) -> str:
  return " ".join(f"{float(v):.9g}" for v in np.ravel(x))


def tool_xml(parts, densities, *, textures: bool = False, inertial=None) -> str:
  """MJCF of the tool on the ground: convex-piece mesh geoms (part i's named part{i}_j,
  material mat{i} when `textures`) in one free body with the parts' exact inertia, or
  `inertial` = (mass, centre of mass, inertia about it) in the tool's frame instead."""
  mass, com, inertia = mass_properties(parts, densities) if inertial is None else inertial
  meshes, geoms = [], []
  for i, part in enumerate(parts):
    for j, piece in enumerate(convex_pieces(part)):
      meshes.append(f'    <mesh name="part{i}_{j}" vertex="{_floats(piece)}"/>')
      material = f' material="mat{i}"' if textures else ""
      geoms.append(f'      <geom name="part{i}_{j}" type="mesh" mesh="part{i}_{j}"{material}/>')
  full = _floats([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                  inertia[1, 2]])
  return f"""<mujoco model="ppdjax_tool">
  <compiler inertiafromgeom="false"/>
{scene.OPTION_XML}
  <asset>
{chr(10).join(meshes)}
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
    <body name="object" pos="0 0 {rest_height(parts):.9g}">
      <freejoint name="object"/>
      <inertial pos="{_floats(com)}" mass="{mass:.9g}" fullinertia="{full}"/>
{chr(10).join(geoms)}
    </body>
  </worldbody>
</mujoco>"""


def _ray_hull(origin, direction, points) -> float:
  """Entry distance of a ray into the convex hull of points (inf if it misses)."""
  hull = trimesh.convex.convex_hull(points)
  normals, offsets = hull.face_normals, np.einsum("ij,ij->i", hull.face_normals,
                                                  hull.triangles[:, 0])
  along, gap = normals @ direction, offsets - normals @ origin
  enter = np.max(np.where(along < 0, gap / np.where(along < 0, along, -1), -np.inf))
  leave = np.min(np.where(along > 0, gap / np.where(along > 0, along, 1), np.inf))
  if np.any((np.abs(along) < 1e-12) & (gap < 0)) or enter > leave or leave < 0:
    return np.inf
  return max(enter, 0.0)


def push_points(parts, pushes: Pushes) -> np.ndarray:
  """(P, 3) where each push acts: the first hit of the ray source -> target on the tool's
  convex pieces, or the target itself if the ray misses (the towers' rule)."""
  pieces = [p for part in parts for p in convex_pieces(part)]
  out = []
  for source, target in zip(np.asarray(pushes.sources, np.float64),
                            np.asarray(pushes.targets, np.float64)):
    direction = (target - source) / np.linalg.norm(target - source)
    t = min(_ray_hull(source, direction, p) for p in pieces)
    out.append(source + t * direction if np.isfinite(t) else target)
  return np.asarray(out)


def simulate_tool(parts, densities, pushes: Pushes | None = None, *,
                  steps: int = STEPS, inertial=None) -> np.ndarray:
  """(P, steps, 7) poses (object-frame origin, quaternion w x y z) of the tool under each
  push (default `tool_pushes()`), by MuJoCo C with MuJoCo's default solver settings (as
  `backend="mujoco"`); `inertial` (mass, centre of mass, inertia about it) replaces the
  parts' own (`tool_xml`). Raises RuntimeError if the solver diverges."""
  pushes = tool_pushes() if pushes is None else pushes
  if pushes.is_strike:
    raise ValueError("simulate_tool applies forces; strikes (Pushes.striker_masses) are "
                     "simulated by ppdjax.simulate on boxes")
  import mujoco  # pylint: disable=import-outside-toplevel
  inertial = mass_properties(parts, densities) if inertial is None else inertial
  model = mujoco.MjModel.from_xml_string(tool_xml(parts, densities, inertial=inertial))
  data = mujoco.MjData(model)
  _, com, _ = inertial
  sources = np.asarray(pushes.sources, np.float64)
  directions = np.asarray(pushes.targets, np.float64) - sources
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  forces = directions * np.asarray(pushes.magnitudes, np.float64)[:, None]
  torques = np.cross(push_points(parts, pushes) - com, forces)
  body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
  out = np.zeros((pushes.num, steps, 7))
  for p in range(pushes.num):
    mujoco.mj_resetData(model, data)
    for t in range(steps):
      data.xfrc_applied[body] = np.concatenate([forces[p], torques[p]]) if t < pushes.duration \
          else 0.0
      mujoco.mj_step(model, data)
      out[p, t] = data.qpos[:7]
    if data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number:
      raise RuntimeError(f"the simulation diverged under push {p} (force "
                         f"{np.linalg.norm(forces[p]):g} N on a {model.body_mass[body]:.3g} kg "
                         "tool); use a smaller push")
  return out


def render_tool(parts, materials, texture_seeds, *, height: int = 224, width: int = 224,
                depth: bool = False):
  """(H, W, 3) uint8 image of the tool at rest, each part with its material's texture,
  under the towers' camera and light; with `depth`, (image, (H, W) float32 metres from
  MuJoCo's depth pass)."""
  images, depth_map = render_configs(parts, [materials], [texture_seeds], height=height,
                                     width=width, depth=depth)
  return (images[0], depth_map) if depth else images[0]


def render_configs(parts, materials, texture_seeds, *, height: int = 224, width: int = 224,
                   depth: bool = False, rest_z: float | None = None):
  """(images (C, H, W, 3) uint8, depth (H, W) float32 metres or None) of the parts at rest
  under C texturings: configuration c gives part i the texture of materials[c][i] from
  texture_seeds[c][i]. One model and one GL context serve every configuration (the mesh is
  parsed once). `rest_z`: world z of the object-frame origin (default: the parts' own
  lowest vertex on the ground, `rest_height`)."""
  import mujoco  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import render  # pylint: disable=import-outside-toplevel
  # drawn only: no collision and a shell's inertia, so that an open or flat piece of a
  # surface (a box's share of a tool's faces) compiles (MuJoCo refuses the convex hull of
  # coplanar vertices)
  meshes = "\n".join(
      f'    <mesh name="part{i}" inertia="shell" vertex="{_floats(p.vertices)}" '
      f'face="{_floats(p.faces)}"/>' for i, p in enumerate(parts))
  geoms = "\n".join(f'      <geom name="part{i}" type="mesh" mesh="part{i}" material="mat{i}" '
                    'contype="0" conaffinity="0"/>' for i in range(len(parts)))
  model = mujoco.MjModel.from_xml_string(
      render.stage_xml(render.material_assets(len(parts)), geoms, meshes))
  model.body_pos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")] = (
      0.0, 0.0, rest_height(parts) if rest_z is None else rest_z)
  tex = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, f"tex{i}")
         for i in range(len(parts))]
  data = mujoco.MjData(model)
  mujoco.mj_forward(model, data)
  images = []
  with render.open_renderer(model, height, width) as renderer:
    for config_materials, config_seeds in zip(materials, texture_seeds):
      renderer._gl_context.make_current()  # pylint: disable=protected-access
      for i, (material, seed) in enumerate(zip(config_materials, config_seeds)):
        render.write_texture(model, tex[i], material, int(seed))
        mujoco.mjr_uploadTexture(model, renderer._mjr_context, tex[i])  # pylint: disable=protected-access
      renderer.update_scene(data, camera="view")
      images.append(renderer.render().copy())
    depth_map = None
    if depth:
      renderer.enable_depth_rendering()
      renderer.update_scene(data, camera="view")
      depth_map = renderer.render().astype(np.float32)
  return np.stack(images), depth_map


def observe(parts, materials, densities, texture_seeds, *, image_size: int = 224,
            steps: int = STEPS, pushes: Pushes | None = None,
            trajectories: bool = True) -> dict[str, np.ndarray]:
  """What the model observes of a tool (normalised parts): "voxels" (32, 32, 32) uint8,
  "image" (S, S, 3) uint8, "depth" (S, S) float32, "trajectories" (P, steps, 7) float32
  under `pushes` (default `tool_pushes()`; left out with trajectories=False). Raises
  RuntimeError if the simulation diverges."""
  traj = simulate_tool(parts, densities, pushes, steps=steps) if trajectories else None
  union, _ = voxelize_parts(parts)
  image, depth = render_tool(parts, materials, texture_seeds, height=image_size,
                             width=image_size, depth=True)
  out = {"voxels": union.astype(np.uint8), "image": image, "depth": depth}
  return out if traj is None else {**out, "trajectories": traj.astype(np.float32)}
