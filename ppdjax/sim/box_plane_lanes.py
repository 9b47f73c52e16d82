"""The box-plane step written per lane, for `box_plane_kernel`'s GPU kernel.

A rollout's scalars are (BLOCK,) arrays (one lane per rollout), its vectors and matrices
tuples of them (the kernel language has no small arrays of odd sizes); its contact
candidates (4 per box, padded to CANDIDATES) are (CANDIDATES, BLOCK) tensors, and the
kept contacts are packed into (max_contacts, BLOCK) tensors before the solve, so a row
operation is one tensor operation. The physics is `box_plane.step`'s: contacts by
`mjc_PlaneBox`, the deepest `max_contacts` as `top_k` picks them, pyramidal soft rows
written through the contact points' velocities (a row times a joint-space vector is
edge . (v + omega x arm)), MuJoCo's Newton solver with MJX's line search, semi-implicit
Euler. tests/test_physics.py holds the kernel to the reference step.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ppdjax.conventions import TIMESTEP
from ppdjax.sim import box_plane, newton
from ppdjax.sim.box_plane import FRICTION, GRAVITY
from ppdjax.sim.newton import LS_TOLERANCE, MINVAL, TOLERANCE
from ppdjax.sim.small_linalg import cholesky_solve_entries

CANDIDATES = 32  # contact candidates per rollout (4 per box, then invalid padding)


# --- scalar algebra on tuples -------------------------------------------------------------

def _dot(a, b):
  return functools.reduce(lambda x, y: x + y, [x * y for x, y in zip(a, b)])


def _cross(a, b):
  return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _mv(m, v):  # m: rows
  return tuple(_dot(row, v) for row in m)


def _mtv(m, v):  # m transposed, times v
  return tuple(_dot([m[k][j] for k in range(len(v))], v) for j in range(len(m[0])))


_where = newton.pick


def _quat_to_rows(q):
  w, x, y, z = q
  return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
          (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
          (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


# --- the step -------------------------------------------------------------------------------

def _mass_matrix(body, rot):
  """6x6 rows of MuJoCo's M for the free joint (box_plane._mass_matrix)."""
  m, c, inertia = body["mass"], body["com"], body["inertia"]
  skew = ((0.0, -c[2], c[1]), (c[2], 0.0, -c[0]), (-c[1], c[0], 0.0))
  rc = tuple(tuple(-m * _dot(rot[i], [skew[k][j] for k in range(3)]) for j in range(3))
             for i in range(3))  # -m rot skew(c)
  cc = _dot(c, c)
  br = tuple(tuple(inertia[i][j] - m * (c[i] * c[j] - (cc if i == j else 0.0))
                   for j in range(3)) for i in range(3))
  eye = lambda i, j: m if i == j else 0.0 * m
  return tuple(tuple(eye(i, j) for j in range(3)) + rc[i] for i in range(3)) + tuple(
      tuple(rc[j][i] for j in range(3)) + br[i] for i in range(3))


def _smooth_force(body, rot, qvel, wrench):
  m, inertia = body["mass"], body["inertia"]
  omega_b = qvel[3:]
  omega, r = _mv(rot, omega_b), _mv(rot, body["com"])
  centripetal = _cross(omega, _cross(omega, r))
  force = tuple(m * GRAVITY[i] + wrench[i] - m * centripetal[i] for i in range(3))
  torque = _mtv(rot, tuple(a + b for a, b in zip(_cross(r, force), wrench[3:])))
  gyro = _cross(omega_b, _mv(inertia, omega_b))
  return force + tuple(t - g for t, g in zip(torque, gyro))


def _contacts(body, pos, rot, max_contacts):
  """Contacts as (slots, BLOCK) tensors: depth, arm (point - origin, world) and `on`.

  All candidates (4 per box) are tested; with `max_contacts`, the deepest touching ones
  are then packed into max_contacts slots (rounded up to a power of two), deepest first
  and the lowest index on ties, as `lax.top_k` picks them, so the solver works on those
  rows only."""
  centre = [sum(rot[i][j] * body["cand_pos"][j] for j in range(3)) for i in range(3)]
  corner = [sum(rot[i][j] * body["cand_corner"][j] for j in range(3)) for i in range(3)]
  down = corner[2] <= 0.0
  corner = [jnp.where(down, x, -x) for x in corner]
  depth = pos[2] + centre[2] + corner[2]
  arm = (centre[0] + corner[0], centre[1] + corner[1], centre[2] + corner[2] - 0.5 * depth)
  on = ((depth <= 0.0) & body["cand_valid"]).astype(jnp.float32)
  if not 0 < max_contacts < body["num_candidates"]:
    return depth, arm, on
  index = jax.lax.broadcasted_iota(jnp.int32, depth.shape, 0)
  key = jnp.where(on > 0, -depth, -1e30)  # untouching candidates rank below all others
  slots = 1 << (max_contacts - 1).bit_length()
  slot = jax.lax.broadcasted_iota(jnp.int32, (slots, depth.shape[1]), 0)
  fields = (depth,) + arm + (on,)
  packed = [jnp.zeros(slot.shape, jnp.float32) for _ in fields]
  kept = jnp.zeros(depth.shape, bool)
  for r in range(max_contacts):
    best = jnp.max(jnp.where(kept, -jnp.inf, key), axis=0)
    first = jnp.min(jnp.where(~kept & (key == best), index, CANDIDATES), axis=0)
    pick = index == first
    kept = kept | pick
    packed = [jnp.where(slot == r, jnp.sum(jnp.where(pick, f, 0.0), axis=0), p)
              for f, p in zip(fields, packed)]
  return packed[0], tuple(packed[1:4]), packed[4]


def _edge_speeds(c, x):
  """J x: the 4 pyramid rows' speeds per candidate for a joint-space 6-vector x; a row is
  edge . (velocity of the contact point), edges (0, mu, 1), (0, -mu, 1), (-mu, 0, 1),
  (mu, 0, 1) in box_plane._constraints' order."""
  omega = _mv(c["rot"], x[3:])
  w = [x[i] + o for i, o in enumerate(_cross(omega, c["arm"]))]
  mu, on = FRICTION, c["on"]
  return (on * (mu * w[1] + w[2]), on * (w[2] - mu * w[1]), on * (w[2] - mu * w[0]),
          on * (mu * w[0] + w[2]))


def _edge_forces(c, f):
  """J' f: the joint-space force of per-row forces f (4 tensors)."""
  mu, on = FRICTION, c["on"]
  force = (on * mu * (f[3] - f[2]), on * mu * (f[0] - f[1]), on * (f[0] + f[1] + f[2] + f[3]))
  lin = tuple(jnp.sum(x, axis=0) for x in force)
  torque = tuple(jnp.sum(x, axis=0) for x in _cross(c["arm"], force))
  return lin + _mtv(c["rot"], torque)


def _edge_hessian(c, w):
  """sum over rows of w J J' (6x6 rows) for per-row weights w (4 tensors): per candidate
  J = [I; rot' K] e with K = skew(arm), so the sum is [S, S K' rot; rot' K S, rot' K S K' rot]
  with S the candidate's sum of w e e'."""
  mu2, mu = FRICTION ** 2, FRICTION
  zero = jnp.zeros_like(w[0])
  s = ((mu2 * (w[2] + w[3]), zero, mu * (w[3] - w[2])),
       (zero, mu2 * (w[0] + w[1]), mu * (w[0] - w[1])),
       (mu * (w[3] - w[2]), mu * (w[0] - w[1]), w[0] + w[1] + w[2] + w[3]))
  a = c["arm"]
  k = ((0.0, -a[2], a[1]), (a[2], 0.0, -a[0]), (-a[1], a[0], 0.0))
  ks = [[sum(k[i][m] * s[m][j] for m in range(3)) for j in range(3)] for i in range(3)]
  ksk = [[sum(ks[i][m] * k[j][m] for m in range(3)) for j in range(3)] for i in range(3)]
  total = lambda x: jnp.sum(x, axis=0)
  ss = [[total(s[i][j]) for j in range(3)] for i in range(3)]
  b = [[total(ks[i][j]) for j in range(3)] for i in range(3)]
  cc = [[total(ksk[i][j]) if j >= i else None for j in range(3)] for i in range(3)]
  cc = [[cc[min(i, j)][max(i, j)] for j in range(3)] for i in range(3)]
  rot = c["rot"]
  rt = [[rot[j][i] for j in range(3)] for i in range(3)]  # rot'
  mat = lambda x, y: [[sum(x[i][m] * y[m][j] for m in range(3)) for j in range(3)]
                      for i in range(3)]
  al = mat(rt, b)  # rot' K S
  aa = mat(mat(rt, cc), rot)
  return [ss[i] + [al[j][i] for j in range(3)] for i in range(3)] + [
      al[i] + aa[i] for i in range(3)]


def _constraints(body, pos, rot, qvel, max_contacts):
  """The rows' geometry (rot, arm, on), D per candidate and aref per row (4 tensors)."""
  depth, arm, on = _contacts(body, pos, rot, max_contacts)
  c = {"rot": rot, "arm": arm, "on": on}
  k, b, imp = box_plane.impedance(depth)
  invweight = (1.0 / body["mass"]) * (1 + FRICTION ** 2) * 2 * FRICTION ** 2
  d = 1.0 / jnp.maximum(invweight * (1 - imp) / imp, MINVAL)
  aref = tuple(-b * v - k * imp * depth * on for v in _edge_speeds(c, qvel))
  return c, d, aref


def _context(p, qacc):
  return {"qacc": qacc, "ma": _mv(p["m"], qacc),
          "jaref": tuple(v - a for v, a in zip(_edge_speeds(p["c"], qacc), p["aref"]))}


def _update_constraint(p, ctx, prev_cost):
  active = tuple(x < 0 for x in ctx["jaref"])
  force = tuple(jnp.where(a, -p["d"] * x, 0.0) for a, x in zip(active, ctx["jaref"]))
  gauss = 0.5 * _dot([a - b for a, b in zip(ctx["ma"], p["qfrc_smooth"])],
                     [a - b for a, b in zip(ctx["qacc"], p["qacc_smooth"])])
  rows = sum(jnp.where(a, p["d"] * x * x, 0.0) for a, x in zip(active, ctx["jaref"]))
  return dict(ctx, active=active, gauss=gauss, cost=gauss + 0.5 * jnp.sum(rows, axis=0),
              prev_cost=prev_cost, qfrc_constraint=_edge_forces(p["c"], force))


def _update_gradient(p, ctx):
  grad = tuple(a - b - c for a, b, c in zip(ctx["ma"], p["qfrc_smooth"], ctx["qfrc_constraint"]))
  rows = _edge_hessian(p["c"], [jnp.where(a, p["d"], 0.0) for a in ctx["active"]])
  h = [[p["m"][i][j] + rows[i][j] for j in range(6)] for i in range(6)]
  mgrad = cholesky_solve_entries(h, grad)
  return dict(ctx, grad=grad, mgrad=mgrad, search=tuple(-x for x in mgrad))


def _linesearch(p, ctx, ls_iterations):
  """MJX's bracketing Newton line search (newton._linesearch), rows as tensors."""
  search = ctx["search"]
  gtol = TOLERANCE * LS_TOLERANCE * jnp.sqrt(_dot(search, search)) * p["trace_m"]
  mv = _mv(p["m"], search)
  jv = _edge_speeds(p["c"], search)
  qg = (ctx["gauss"], _dot(search, [a - b for a, b in zip(ctx["ma"], p["qfrc_smooth"])]),
        0.5 * _dot(search, mv))
  d = p["d"]
  quad = [(0.5 * d * x * x, d * v * x, 0.5 * d * v * v) for x, v in zip(ctx["jaref"], jv)]

  def point(alpha):
    on = [(x + alpha * v) < 0 for x, v in zip(ctx["jaref"], jv)]
    q = [qg[i] + jnp.sum(sum(jnp.where(o, qu[i], 0.0) for o, qu in zip(on, quad)), axis=0)
         for i in range(3)]
    return {"alpha": alpha, "cost": alpha * alpha * q[2] + alpha * q[1] + q[0],
            "d0": 2 * alpha * q[2] + q[1],
            "d1": 2 * q[2] + jnp.where(q[2] == 0, MINVAL, 0.0)}

  p0 = point(jnp.zeros_like(gtol))
  rows_0 = jnp.maximum(p0["cost"] - qg[0], 0.0)
  rows_2 = jnp.maximum(0.5 * p0["d1"] - qg[2], 0.0)
  dmag = 2.0 * jnp.sqrt(rows_0 * rows_2) + jnp.abs(qg[1])
  gtol_accept = jnp.maximum(gtol, 8 * float(np.finfo(np.float32).eps) * dmag)
  first = point(p0["alpha"] - p0["d0"] / p0["d1"])
  better = first["d0"] < p0["d0"]
  lo, hi = _where(better, first, p0), _where(better, p0, first)

  def good(x):
    return (jnp.abs(x["d0"]) < gtol_accept) & (x["cost"] < p0["cost"])

  lo, hi, _ = jax.lax.fori_loop(
      0, ls_iterations, lambda _, c: newton.bracket_iteration(point, good, *c),
      (lo, hi, jnp.ones(gtol.shape, bool)))
  improved = (lo["cost"] < p0["cost"]) | (hi["cost"] < p0["cost"])
  alpha = jnp.where(improved, jnp.where(lo["cost"] < hi["cost"], lo["alpha"], hi["alpha"]), 0.0)
  return dict(ctx, qacc=tuple(a + alpha * s for a, s in zip(ctx["qacc"], search)),
              ma=tuple(a + alpha * s for a, s in zip(ctx["ma"], mv)),
              jaref=tuple(a + alpha * s for a, s in zip(ctx["jaref"], jv)))


def _solve(p, warmstart, iterations, ls_iterations):
  """newton.solve per scalar: qacc after `iterations` Newton steps, converged frozen."""
  inf = jnp.full_like(p["trace_m"], jnp.inf)
  warm = _update_constraint(p, _context(p, warmstart), inf)
  smooth = _update_constraint(p, _context(p, p["qacc_smooth"]), inf)
  start = _where(warm["cost"] < smooth["cost"], warmstart, p["qacc_smooth"])
  ctx = _update_gradient(p, _update_constraint(p, _context(p, start), inf))

  def iteration(_, ctx):
    improvement = (ctx["prev_cost"] - ctx["cost"]) / p["trace_m"]
    gradient = jnp.sqrt(_dot(ctx["grad"], ctx["grad"])) / p["trace_m"]
    go = (improvement >= TOLERANCE) & (gradient >= TOLERANCE)
    probe = dict(ctx, search=tuple(jnp.where(go, s, 1.0) for s in ctx["search"]))
    new = _linesearch(p, probe, ls_iterations)
    new = _update_gradient(p, _update_constraint(p, new, ctx["cost"]))
    return _where(go, new, ctx)

  return jax.lax.fori_loop(0, iterations, iteration, ctx)["qacc"]


def step(body, qpos, qvel, warm, wrench, iterations, ls_iterations, max_contacts):
  """box_plane.step per lane: (qpos 7, qvel 6, qacc 6) tuples of (BLOCK,) arrays.

  `body` holds the unpacked fields of `box_plane_kernel` (scalars, and candidate tensors
  "cand_pos", "cand_corner", "cand_valid") and "num_candidates" (4 per box)."""
  norm = jnp.sqrt(_dot(qpos[3:], qpos[3:]))
  pos, quat = qpos[:3], tuple(x / norm for x in qpos[3:])
  rot = _quat_to_rows(quat)
  m = _mass_matrix(body, rot)
  qfrc_smooth = _smooth_force(body, rot, qvel, wrench)
  c, d, aref = _constraints(body, pos, rot, qvel, max_contacts)
  trace = functools.reduce(lambda a, b: a + b, [m[i][i] for i in range(6)])
  problem = {"m": m, "qfrc_smooth": qfrc_smooth,
             "qacc_smooth": cholesky_solve_entries(m, qfrc_smooth),
             "c": c, "d": d, "aref": aref, "trace_m": jnp.maximum(trace, MINVAL)}
  qacc = _solve(problem, warm, iterations, ls_iterations)
  qvel = tuple(v + TIMESTEP * a for v, a in zip(qvel, qacc))
  return (tuple(p + TIMESTEP * v for p, v in zip(pos, qvel[:3]))
          + _quat_integrate(quat, qvel[3:]), qvel, qacc)


def _quat_integrate(quat, omega_b):
  """box_plane._quat_integrate per scalar (mju_quatIntegrate)."""
  sq = _dot(omega_b, omega_b)
  norm = jnp.sqrt(jnp.where(sq > 0, sq, 1.0))
  half = 0.5 * TIMESTEP * norm
  scale = jnp.where(sq > 0, jnp.sin(half) / norm, 0.5 * TIMESTEP)
  w, v = jnp.cos(jnp.where(sq > 0, half, 0.0)), tuple(scale * x for x in omega_b)
  a0, a = quat[0], quat[1:]
  cr = _cross(a, v)
  out = (a0 * w - _dot(a, v),) + tuple(a0 * vi + w * ai + ci for vi, ai, ci in zip(v, a, cr))
  n = jnp.sqrt(_dot(out, out))
  return tuple(x / n for x in out)
