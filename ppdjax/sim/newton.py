"""MuJoCo's Newton solver for one free body's pyramidal contact constraints (as MJX runs it).

Minimises over qacc the Gauss cost 0.5 (qacc - qacc_smooth)' M (qacc - qacc_smooth) plus
0.5 D (J qacc - aref)^2 over the active rows (J qacc < aref), with MJX's warm start,
bracketing Newton line search and stopping test, for a fixed number of iterations: each
element is frozen once converged, as `ppdjax.sim.mjx_step.solve` does, so there is no
`while_loop` and reverse mode works. Used by `ppdjax.sim.box_plane`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ppdjax.sim.small_linalg import cholesky_solve

TOLERANCE, LS_TOLERANCE = 1e-8, 0.01  # MuJoCo's solver defaults
MINVAL = 1e-15  # mjMINVAL


@struct.dataclass
class _Ctx:
  qacc: jax.Array
  ma: jax.Array
  jaref: jax.Array
  grad: jax.Array
  mgrad: jax.Array
  search: jax.Array
  gauss: jax.Array
  cost: jax.Array
  prev_cost: jax.Array
  active: jax.Array
  qfrc_constraint: jax.Array


@struct.dataclass
class Problem:
  """The Newton problem of one step: min over qacc of the Gauss + constraint cost."""

  m: jax.Array  # (6, 6)
  qfrc_smooth: jax.Array
  qacc_smooth: jax.Array
  j: jax.Array  # (R, 6)
  d: jax.Array  # (R,)
  aref: jax.Array  # (R,)
  trace_m: jax.Array


def _update_constraint(p: Problem, ctx: _Ctx) -> _Ctx:
  active = ctx.jaref < 0
  force = -p.d * ctx.jaref * active
  gauss = 0.5 * jnp.dot(ctx.ma - p.qfrc_smooth, ctx.qacc - p.qacc_smooth)
  cost = 0.5 * jnp.sum(p.d * ctx.jaref * ctx.jaref * active) + gauss
  return ctx.replace(active=active, gauss=gauss, cost=cost, prev_cost=ctx.cost,
                     qfrc_constraint=p.j.T @ force)


def _update_gradient(p: Problem, ctx: _Ctx) -> _Ctx:
  grad = ctx.ma - p.qfrc_smooth - ctx.qfrc_constraint
  h = p.m + (p.j.T * (p.d * ctx.active)) @ p.j
  return ctx.replace(grad=grad, mgrad=cholesky_solve(0.5 * (h + h.T), grad))


def _context(p: Problem, qacc: jax.Array, grad: bool = True) -> _Ctx:
  zero = jnp.zeros(6, qacc.dtype)
  ctx = _Ctx(qacc=qacc, ma=p.m @ qacc, jaref=p.j @ qacc - p.aref, grad=zero, mgrad=zero,
             search=zero, gauss=jnp.zeros(()), cost=jnp.array(jnp.inf),
             prev_cost=jnp.zeros(()), active=jnp.zeros(p.d.shape, bool),
             qfrc_constraint=zero)
  ctx = _update_constraint(p, ctx)
  if grad:
    ctx = _update_gradient(p, ctx)
    ctx = ctx.replace(search=-ctx.mgrad)
  return ctx


def pick(cond, a, b):
  """`a` where `cond`, else `b`, leaf by leaf (pytrees of one structure)."""
  return jax.tree.map(lambda x, y: jnp.where(cond, x, y), a, b)


def _in_bracket(x, y):
  return ((x < y) & (y < 0)) | ((x > y) & (y > 0))


def bracket_iteration(point, good, lo, hi, swap):
  """One iteration of MJX's bracketing Newton line search: Newton steps from both ends
  of the bracket [lo, hi] and its midpoint; the bracket shrinks onto the sign change of
  the slope, or ends on the lowest-cost converged candidate (the first on ties).

  `point(alpha)` gives a dict of "alpha", "cost", "d0" (slope), "d1" (curvature);
  `good(x)` whether a point is converged. Written on whatever arrays the points hold:
  one element here, a block of rollouts in `box_plane_lanes`.
  """
  go = swap & ~good(lo) & ~good(hi)
  lo_next = point(lo["alpha"] - lo["d0"] / lo["d1"])
  hi_next = point(hi["alpha"] - hi["d0"] / hi["d1"])
  mid = point(0.5 * (lo["alpha"] + hi["alpha"]))
  s1 = _in_bracket(lo["d0"], lo_next["d0"])
  new_lo = pick(s1, lo_next, lo)
  s2 = _in_bracket(new_lo["d0"], mid["d0"])
  new_lo = pick(s2, mid, new_lo)
  s3 = _in_bracket(new_lo["d0"], hi_next["d0"])
  new_lo = pick(s3, hi_next, new_lo)
  s4 = _in_bracket(hi["d0"], hi_next["d0"]) | ((hi["d0"] < 0) & (hi_next["d0"] > 0))
  new_hi = pick(s4, hi_next, hi)
  s5 = _in_bracket(new_hi["d0"], mid["d0"])
  new_hi = pick(s5, mid, new_hi)
  s6 = _in_bracket(new_hi["d0"], lo_next["d0"])
  new_hi = pick(s6, lo_next, new_hi)
  new_swap = s1 | s2 | s3 | s4 | s5 | s6
  best, best_cost = lo_next, jnp.where(good(lo_next), lo_next["cost"], jnp.inf)
  for c in (hi_next, mid):
    c_cost = jnp.where(good(c), c["cost"], jnp.inf)
    best, best_cost = pick(c_cost < best_cost, c, best), jnp.minimum(c_cost, best_cost)
  done = good(lo_next) | good(hi_next) | good(mid)
  new_lo, new_hi = pick(done, best, new_lo), pick(done, best, new_hi)
  new_swap = new_swap & ~done
  return pick(go, new_lo, lo), pick(go, new_hi, hi), jnp.where(go, new_swap, swap)


def _linesearch(p: Problem, ctx: _Ctx, ls_iterations: int) -> _Ctx:
  """MJX's bracketing Newton line search on the piecewise quadratic cost (pyramidal)."""
  gtol = TOLERANCE * LS_TOLERANCE * jnp.linalg.norm(ctx.search) * p.trace_m
  mv, jv = p.m @ ctx.search, p.j @ ctx.search
  quad_gauss = jnp.stack([ctx.gauss, jnp.dot(ctx.search, ctx.ma - p.qfrc_smooth),
                          0.5 * jnp.dot(ctx.search, mv)])
  quad = p.d[:, None] * jnp.stack([0.5 * ctx.jaref ** 2, jv * ctx.jaref, 0.5 * jv * jv], 1)

  def point(alpha):
    active = (ctx.jaref + alpha * jv) < 0
    q = quad_gauss + jnp.sum(quad * active[:, None], 0)
    return dict(alpha=alpha, cost=alpha * alpha * q[2] + alpha * q[1] + q[0],
                d0=2 * alpha * q[2] + q[1], d1=2 * q[2] + (q[2] == 0) * MINVAL)

  p0 = point(jnp.zeros(()))
  rows_0 = jnp.maximum(p0["cost"] - quad_gauss[0], 0.0)
  rows_2 = jnp.maximum(0.5 * p0["d1"] - quad_gauss[2], 0.0)
  dmag = 2.0 * jnp.sqrt(jax.lax.stop_gradient(rows_0 * rows_2)) + jnp.abs(quad_gauss[1])
  gtol_accept = jax.lax.stop_gradient(
      jnp.maximum(gtol, 8 * jnp.finfo(dmag.dtype).eps * dmag))
  first = point(p0["alpha"] - p0["d0"] / p0["d1"])
  lo = pick(first["d0"] < p0["d0"], first, p0)
  hi = pick(first["d0"] < p0["d0"], p0, first)
  swap = jnp.array(True)

  def good(x):
    return (jnp.abs(x["d0"]) < gtol_accept) & (x["cost"] < p0["cost"])

  for _ in range(ls_iterations):
    lo, hi, swap = bracket_iteration(point, good, lo, hi, swap)

  improved = (lo["cost"] < p0["cost"]) | (hi["cost"] < p0["cost"])
  alpha = jnp.where(lo["cost"] < hi["cost"], lo["alpha"], hi["alpha"]) * improved
  return ctx.replace(qacc=ctx.qacc + alpha * ctx.search, ma=ctx.ma + alpha * mv,
                     jaref=ctx.jaref + alpha * jv)


def solve(p: Problem, qacc_warmstart: jax.Array, iterations: int,
           ls_iterations: int) -> jax.Array:
  """qacc by `iterations` Newton steps from the better of warm start and smooth."""
  warm = _context(p, qacc_warmstart, grad=False)
  smooth = _context(p, p.qacc_smooth, grad=False)
  ctx = _context(p, jnp.where(warm.cost < smooth.cost, qacc_warmstart, p.qacc_smooth))
  for _ in range(iterations):
    improvement = (ctx.prev_cost - ctx.cost) / p.trace_m
    gradient = jnp.linalg.norm(ctx.grad) / p.trace_m
    go = (improvement >= TOLERANCE) & (gradient >= TOLERANCE)
    # A converged element searches along a harmless unit direction (its result is
    # discarded), so reverse mode sees no 0/0.
    probe = ctx.replace(search=jnp.where(go, ctx.search, jnp.ones_like(ctx.search)))
    new = _linesearch(p, probe, ls_iterations)
    new = _update_gradient(p, _update_constraint(p, new))
    new = new.replace(search=-new.mgrad)
    ctx = jax.tree.map(lambda a, b: jnp.where(go, a, b), new, ctx)
  return ctx.qacc
