"""Boxes fitted to voxels, refined against the RGB image's edges: the image is one of the
paper's three inputs, and where one block meets another (or the floor) it shows an edge
far finer than a voxel.

Each face of the voxel fit moves within half a voxel (where the voxels allow it, as in
`depth_fit`), touching faces together, to where the boxes' rendered outline lies on the
image's strongest colour edges: the boxes are ray cast into a label image (which face of
which box each pixel sees first, or none; with the scene's light, also which pixels lie in
a box's shadow), and the score is the image's colour difference summed over neighbouring
pixel pairs whose labels differ (`edge_score`). The score is
piecewise constant in a face's position (a label changes when an edge crosses a pixel's
centre), so the faces are placed by `depth_fit.sweep_faces`, face by face, in `passes`
sweeps: each face to the middle of the run of positions that score best. A face whose
outline no pixel sees keeps the voxels' verdict.

An object stands on the floor wherever its frame's origin is, so the image shows heights
above the floor and never where along z the origin sits: the faces on the floor stay and the
other z faces may move a whole voxel (`face_spans`). The sweep is local, so it runs from
two starts (`STARTS`): sharp edges alone, and a sweep on blurred edges first; the faces
with the better sharp score win. Every sweep of every start is one step of one loop, so
the sweep compiles once. A sweep visits the valid boxes' faces only, and a batch goes
through in chunks of objects with as many boxes.

Where JAX runs on a CPU, each face's positions are scored only on the rectangle of pixels
they can change (the face's slab and its shadow: `image_regions`), in small tiles: the
same faces as scoring the whole window, 16x faster on 24 rendered towers. On a GPU the
whole window is scored at once, and each chunk's labels test only as many box slots as
its objects have (`depth_fit.map_by_box_count(slots=True)`).

What each part buys, measured: docs/inference.md, "With the image".
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.dataset.camera import check_camera
from ppdjax.dataset.depth import camera_rays, to_world
from ppdjax.infer import image_regions
from ppdjax.infer.image_edges import blur_strength, edge_score, edge_strength
from ppdjax.infer.depth_fit import (MIN_HALF, SWEEP_COARSE, SWEEP_FINE, TOUCHING, VOXEL,
                                    boxes_from_faces, map_by_box_count, sweep_faces,
                                    touching_faces)
from ppdjax.primitives import Primitives, lowest_point, quat_to_mat

# Each start's sweeps first on edges blurred over these many pixels (wider basins), then
# `passes` on the sharp edges; the start that ends on the best sharp score wins. Measured on
# 32 towers of the split's two-block tail (docs/inference.md): face error p90 7.4 mm with the
# sharp sweeps alone, 5.8 with a blurred sweep first, 4.8 with the better of both.
STARTS = ((), (2.0,))
PASSES = 2  # sweeps over every face (the second places faces whose neighbours moved)
SWEEP = (SWEEP_COARSE, SWEEP_FINE)  # a sweep's offsets per face: over its interval, per end
# objects refined together (224² pixels x 33 positions x K boxes per face); on an H100 8 and
# 16 are as fast, 32 and 64 slower (experiments/benchmarks/bench_image_fit.py)
CHUNK = 8
SHADOW_EPS = 1e-4  # a shadow ray leaving a box this soon (its exit parameter, m) is not
# blocked by it: a point on a lit face leaves its own box at 0


def face_labels(prims: Primitives, origin, dirs_Nx3, light=None) -> jax.Array:
  """(N,) int: per ray, 6·k + f for the face f (`metrics.FACE_NAMES` order: x, y, z lo,
  then hi, along box k's own axes) of the valid box k it meets first; 6·K where it meets
  none. Boxes of one object (object frame) at rest, as the dataset renders them.

  With `light` (3,), the direction a directional light's rays travel (`camera.LIGHT_DIR`),
  each label is doubled and 1 is added where the point the ray meets (a face, or the floor
  z = 0) lies in a box's shadow: shadow outlines then count as edges of the labels.
  """
  return labeller(prims, origin, dirs_Nx3, light)(prims)


def labeller(prims: Primitives, origin, dirs_Nx3, light=None):
  """`face_labels` as a function of boxes with the rotations of `prims` (the sweep moves
  faces only): the rays' directions in each box's frame are computed once.

  Written box by box and axis by axis over (N,) arrays, the nearest box and its entry
  face kept by comparisons (an arg-min and gathers over (N, K, 3) arrays ran 6x slower
  on a CPU, with the same labels: experiments/results/benchmarks.md, the front door)."""
  rot = quat_to_mat(prims.quat)  # (K, 3, 3); at rest the object is only lifted
  d_all = jnp.moveaxis(_nonzero(jnp.einsum("kji,nj->nki", rot, dirs_Nx3)), 0, -1)  # (K, 3, N)
  inv_d_all = 1.0 / d_all
  if light is not None:  # from each point toward the light, in the box frames
    toward = -jnp.asarray(light, jnp.float32) / jnp.linalg.norm(jnp.asarray(light, jnp.float32))
    inv_light = 1.0 / _nonzero(jnp.einsum("kji,j->ki", rot, toward))  # (K, 3)
  down_all = dirs_Nx3[:, 2] < -1e-9  # rays that meet the floor unless a box is in the way
  t_floor_all = jnp.where(down_all, -origin[2] / jnp.where(down_all, dirs_Nx3[:, 2], -1.0), 0.0)
  num_slots = prims.valid.shape[-1]
  empty = 6 * num_slots

  def labels(boxes: Primitives, rays=None) -> jax.Array:
    """The labels of every ray, or of the rays `rays` (M,) int only."""
    world = to_world(boxes)
    d, inv_d, t_floor, down = ((d_all, inv_d_all, t_floor_all, down_all) if rays is None else
                               (d_all[..., rays], inv_d_all[..., rays], t_floor_all[rays],
                                down_all[rays]))
    o = jnp.einsum("kji,kj->ki", rot, origin[None] - world.pos)  # (K, 3) camera, box frames
    h = world.half_size
    t_best = jnp.full(d.shape[-1], jnp.inf, d.dtype)
    out = jnp.full(d.shape[-1], empty, jnp.int32)
    for k in range(num_slots):  # the first box at the least entry wins (arg-min's tie)
      near, far = _slab(o[k][:, None], inv_d[k], h[k][:, None])
      t_in = jnp.maximum(jnp.maximum(near[0], near[1]), near[2])
      t_out = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
      hit = (t_in <= t_out) & (t_out > 0) & world.valid[k]
      # the entry axis (the first of the largest near parameters, as arg-max) and side
      axis = jnp.where(near[0] >= jnp.maximum(near[1], near[2]), 0,
                       jnp.where(near[1] >= near[2], 1, 2))
      d_axis = jnp.where(axis == 0, d[k, 0], jnp.where(axis == 1, d[k, 1], d[k, 2]))
      label = 6 * k + axis + jnp.where(d_axis > 0, 0, 3)  # entering a lower face: up the axis
      closer = hit & (t_in < t_best)
      t_best = jnp.where(closer, t_in, t_best)
      out = jnp.where(closer, label, out)
    if light is not None:
      any_hit = t_best < jnp.inf
      seen = any_hit | down  # rays into the sky meet nothing
      t = jnp.where(any_hit, t_best, jnp.where(seen, t_floor, 0.0))
      shadow = jnp.zeros(d.shape[-1], bool)
      for k in range(num_slots):  # where each ray ends, toward the light, through box k
        points = o[k][:, None] + t[None] * d[k]  # (3, N) in box k's frame
        near, far = _slab(points, inv_light[k][:, None], h[k][:, None])
        t_in = jnp.maximum(jnp.maximum(near[0], near[1]), near[2])
        t_out = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
        # a point on a lit face leaves its own box at once (exit 0): SHADOW_EPS keeps it lit
        shadow = shadow | ((t_in <= t_out) & (t_out > SHADOW_EPS) & world.valid[k])
      out = 2 * out + (shadow & seen)
    # Read back through an identity gather XLA cannot see through: otherwise it fuses
    # this whole computation into each of `edge_score`'s four shifted reads and runs it
    # four times over (10x slower per scored render on a CPU).
    zero = jnp.minimum(jnp.sum(world.valid), 0)
    return out.at[jnp.arange(out.shape[0]) + zero].get(
        mode="promise_in_bounds", unique_indices=True, indices_are_sorted=True)

  return labels


def _slab(o, inv_d, half_size):
  """Per axis (leading 3), the ray parameters where rays (origins `o`, inverse directions
  `inv_d`, in a box's frame) cross its lower and upper slab planes: (near, far)."""
  t1, t2 = (-half_size - o) * inv_d, (half_size - o) * inv_d
  return jnp.minimum(t1, t2), jnp.maximum(t1, t2)


def _nonzero(d):
  return jnp.where(jnp.abs(d) < 1e-9, 1e-9, d)


def face_spans(prims: Primitives, bound: float) -> jax.Array:
  """(K, 6) how far each face may move from the start (`refine_with_image`).

  An object stands on the ground wherever its frame's origin lies (`dataset.depth.to_world`),
  so the image shows heights above the floor, never where along z the frame's origin sits
  (`depth_fit.boxes_from_faces` centres it afterwards). Each face of the voxel fit lies
  within `bound` (half a voxel) of the truth, so a height above the floor lies within
  2·bound: the faces on the floor stay where they are (their height is 0), the other faces
  across z move within 2·bound, and faces across x and y, which the image places on the
  world's axes, within `bound`. (With the floor free and every face within `bound`, a sweep
  that set the lowest face first carried its error up the tower and left the top out of
  reach: tops a voxel too high on 5 % of two-block towers.)"""
  rot = quat_to_mat(prims.quat)
  up = rot[:, 2, :]  # (K, 3) each box axis's z component
  vertical = jnp.tile(jnp.abs(up) > 1.0 - 1e-6, (1, 2))  # faces across z, (K, 6)
  face_z = prims.pos[:, 2:3] + jnp.concatenate([-prims.half_size * up, prims.half_size * up], -1)
  on_floor = vertical & (face_z < lowest_point(prims) + TOUCHING)
  return jnp.where(on_floor, 0.0, jnp.where(vertical, 2.0 * bound, bound))


def refine_with_image(prims: Primitives, image_HW3, intrinsics, camera_from_world, *,
                      bound: float = VOXEL / 2, passes: int = PASSES,
                      window: tuple[int, int, int, int] | None = None,
                      light: tuple[float, float, float] | None = None,
                      starts: tuple[tuple[float, ...], ...] = STARTS,
                      sweep: tuple[int, int] = SWEEP,
                      tile: tuple[int, int] | None = None) -> Primitives:
  """One object's boxes (K, object frame) refined against its image (H, W, 3).

  Args:
    prims: the voxel fit (`fit.fit_boxes`); rotations are kept.
    image_HW3: the observed RGB image (uint8, or floats in [0, 1]), as the dataset stores it.
    intrinsics, camera_from_world: the image's camera (`storage.Dataset.camera`).
    bound: half a voxel (m): how far faces may move from the start (`face_spans`).
    passes: sweeps over every face on the image's sharp edges, per start.
    window: (r0, r1, c0, c1), the only pixels scored (`image_regions.object_window`: where an object
      or its shadow can appear; the score is the same, in a fraction of the time); None: all.
    light: the direction the scene's directional light travels (`camera.LIGHT_DIR`, the
      dataset's): the labels then hold the boxes' shadows too (`face_labels`); None: the
      outline of the boxes alone.
    starts: per start, the blurs (pixels) of the edges in sweeps before the sharp ones
      (`blur_strength`); every start begins at `prims`, and the faces that end on the best
      sharp score win (`STARTS`).
    sweep: (coarse, fine) offsets a sweep scores per face (`depth_fit.sweep_faces`).
    tile: (rows, columns): score each face's positions only where they can change the
      labels, in tiles of this size (`image_regions`; the same ranking of positions);
      None: every pixel of the window.
  """
  h, w = image_HW3.shape[:2]
  r0, r1, c0, c1 = window or (0, h, 0, w)
  origin, dirs = camera_rays(intrinsics, camera_from_world, h, w)
  dirs = dirs[r0:r1, c0:c1].reshape(-1, 3)
  h, w = r1 - r0, c1 - c0
  sharp = edge_strength(image_HW3[r0:r1, c0:c1])
  labels = labeller(prims, origin, dirs, light)
  scorer = lambda strengths: lambda f: edge_score(
      labels(boxes_from_faces(prims, f)).reshape(h, w), *strengths)
  local = None
  if tile is not None:  # each face's positions scored where they can differ only
    project = image_regions.window_projector(intrinsics, camera_from_world, (r0, r1, c0, c1))
    local = lambda strengths: lambda f_a, f_b, move: (lambda f: image_regions.tiled_edge_score(
        functools.partial(labels, boxes_from_faces(prims, f)),
        image_regions.changed_rect(prims, f_a, f_b, move, project, (h, w), light),
        *strengths, tile))
  ties = touching_faces(prims)
  start = jnp.concatenate([-prims.half_size, prims.half_size], -1)  # (K, 6)
  # within `face_spans` of the start, and no box thinner than 2·MIN_HALF
  span = face_spans(prims, bound)
  lo = jnp.concatenate([-prims.half_size - span[:, :3],
                        jnp.maximum(prims.half_size - span[:, 3:], MIN_HALF)], -1)
  hi = jnp.concatenate([jnp.minimum(-prims.half_size + span[:, :3], -MIN_HALF),
                        prims.half_size + span[:, 3:]], -1)
  faces = _run_starts(start, starts, passes, sharp,
                      lambda f, strengths: sweep_faces(
                          f, lo, hi, ties, prims.valid, scorer(strengths),
                          coarse_steps=sweep[0], fine_steps=sweep[1],
                          local=None if local is None else local(strengths)),
                      side_by_side=tile is None)
  # the best sharp score (argmin: the earlier start on a tie)
  faces = faces[jnp.argmin(jax.vmap(scorer(sharp))(faces))]
  out = boxes_from_faces(prims, faces)
  keep = prims.valid[:, None]
  return out.replace(half_size=jnp.where(keep, out.half_size, prims.half_size),
                     pos=jnp.where(keep, out.pos, prims.pos))


def _run_starts(start_Kx6, starts, passes, sharp, sweep_fn, side_by_side: bool):
  """(S, K, 6) the faces each start ends on: its blurred sweeps (`blur_strength`), then
  `passes` sharp ones, in the rounds of one `jax.lax.fori_loop`, so that the sweep
  compiles once. `side_by_side`: each round sweeps every start that has a sweep left under
  one `jax.vmap` (on a GPU 1.1-1.3x faster than one after the other; a start left without
  a sweep idles through the round); otherwise one start's sweep per round (on a CPU the
  vmap buys nothing, and an idle start would cost a sweep)."""
  sigmas = sorted({sigma for b in starts for sigma in b})
  maps = [sharp] + [[blur_strength(x, sigma) for x in sharp] for sigma in sigmas]
  edges = [jnp.stack([m[axis] for m in maps]) for axis in (0, 1)]  # (E, H, W) each
  # each start's sweeps in order, as edge maps (0: sharp)
  plans = [[1 + sigmas.index(sigma) for sigma in b] + [0] * passes for b in starts]
  if side_by_side:  # round r: the r-th sweep of every start that has one
    rounds = [[(i, p[r]) for i, p in enumerate(plans) if r < len(p)]
              for r in range(max(map(len, plans)))]
  else:
    rounds = [[(i, e)] for i, p in enumerate(plans) for e in p]
  if not any(rounds):
    return jnp.broadcast_to(start_Kx6, (len(starts),) + start_Kx6.shape)
  width = max(map(len, rounds))
  # a round with fewer sweeps than the widest idles the other starts (swept, then kept)
  pad = lambda rnd: rnd + [(i, 0) for i in range(len(starts))
                           if i not in {u[0] for u in rnd}][:width - len(rnd)]
  which = jnp.array([[u[0] for u in pad(r)] for r in rounds], jnp.int32)  # (R, W)
  edge = jnp.array([[u[1] for u in pad(r)] for r in rounds], jnp.int32)
  live = jnp.array([[j < len(r) for j in range(width)] for r in rounds], bool)

  def round_(r, faces):
    one = lambda f, e: sweep_fn(f, (edges[0][e], edges[1][e]))
    if width == 1:  # no vmap of one: it would turn the sweep's loops into batched ones
      new = one(faces[which[r, 0]], edge[r, 0])[None]
    else:
      new = jax.vmap(one)(faces[which[r]], edge[r])
    keep = jnp.where(live[r][:, None, None], new, faces[which[r]])
    return faces.at[which[r]].set(keep)

  faces = jnp.broadcast_to(start_Kx6, (len(starts),) + start_Kx6.shape)
  return jax.lax.fori_loop(0, which.shape[0], round_, faces)


def refine_batch(prims: Primitives, images_BxHxWx3, camera: dict, *,
                 passes: int = PASSES, bound: float = VOXEL / 2,
                 starts: tuple[tuple[float, ...], ...] = STARTS,
                 chunk: int = CHUNK, sweep: tuple[int, int] = SWEEP,
                 slots: bool = True, tile="auto") -> Primitives:
  """`refine_with_image` over a batch (B, K) of objects seen by one camera (jitted once per
  image size and option; `chunk` objects at a time, ordered by their number of boxes:
  `depth_fit.map_by_box_count`; with `slots`, each chunk's labels test only as many box
  slots as its objects have valid boxes: the same faces, 1.25x faster on an H100). The
  camera's "light_dir" (the dataset's light unless set to None, `camera.check_camera`)
  adds the boxes' shadows to the outline. `tile`: `refine_with_image`'s; "auto":
  `image_regions.CPU_TILE` where JAX runs on a CPU, the whole window elsewhere."""
  if tile == "auto":
    tile = image_regions.CPU_TILE if jax.default_backend() == "cpu" else None
  if not starts or passes < 0 or chunk < 1 or min(sweep) < 2:
    raise ValueError(f"image fit: need at least one start, passes >= 0, chunk >= 1 and at "
                     f"least 2 offsets per scan, got starts {starts!r}, passes {passes}, "
                     f"chunk {chunk}, sweep {sweep}")
  cam = check_camera(camera)
  light = None if cam["light_dir"] is None else tuple(map(float, cam["light_dir"]))
  return _refine_batch(prims, jnp.asarray(images_BxHxWx3),
                       jnp.asarray(cam["intrinsics"], jnp.float32),
                       jnp.asarray(cam["camera_from_world"], jnp.float32),
                       passes=passes, bound=float(bound), window=image_regions.object_window(cam, light=light),
                       light=light,
                       starts=tuple(tuple(map(float, b)) for b in starts), chunk=int(chunk),
                       sweep=tuple(map(int, sweep)), slots=bool(slots),
                       tile=None if tile is None else tuple(map(int, tile)))


@functools.partial(jax.jit, static_argnames=("passes", "bound", "window", "light", "starts",
                                             "chunk", "sweep", "slots", "tile"))
def _refine_batch(prims, images, intrinsics, camera_from_world, passes, bound, window, light,
                  starts, chunk, sweep, slots, tile):
  one = lambda p, im: refine_with_image(p, im, intrinsics, camera_from_world, bound=bound,
                                        passes=passes, window=window, light=light, starts=starts,
                                        sweep=sweep, tile=tile)
  with jax.default_matmul_precision("highest"):  # GPUs' TF32 default: mm at 2.6 m
    # with tiles, one program for every box count: on the example tower (4 boxes) the
    # chunks' K - 1 branches compiled 3-4x longer and ran no faster
    return map_by_box_count(one, prims, images, chunk=chunk, slots=slots and tile is None)


def check_image(image, camera: dict, batch: tuple[int, ...]) -> None:
  """ValueError naming the problem with an image batch (B..., H, W, 3) for `batch` objects."""
  shape = tuple(np.shape(image))
  if camera is None:
    raise ValueError("image was given without its camera (storage.Dataset.camera)")
  cam = check_camera(camera)
  want = tuple(batch) + (cam["height"], cam["width"], 3)
  if shape != want:
    raise ValueError(f"image: expected shape {want} for the voxels' batch {tuple(batch)} "
                     f"and the camera's {cam['height']}x{cam['width']}, got {shape}")
  if not isinstance(image, jax.core.Tracer):
    a = np.asarray(image)
    if np.issubdtype(a.dtype, np.floating):
      if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
        raise ValueError("image: float values must be finite and in [0, 1] (or pass uint8)")
    elif a.dtype != np.uint8:
      raise ValueError(f"image: expected uint8 or floats in [0, 1], got {a.dtype}")
