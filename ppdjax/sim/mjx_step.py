"""`mjx.step` with a fixed-count Newton solver: no `while_loop`, so no host sync per iteration.

MJX's solver runs `jax.lax.while_loop(cond, body)`; on a GPU each iteration copies its
predicate to the host, which drains the launch queue and dominates small batches. Under
`vmap` MJX already runs the loop to the slowest element and freezes finished elements
with a select. This step does the same without the loop: `iterations` unrolled bodies,
each committed only where MJX's own stopping test says the element is not yet done. So
it computes what `mjx.step` computes (tested), and it is reverse-differentiable too.

It is built from MJX's stage functions (`mujoco.mjx._src`), which are not public API:
pinned by the version range in pyproject.toml and by tests/test_physics.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import forward, math, solver, support
from mujoco.mjx._src.types import ConeType, DisableBit, IntegratorType, SolverType

from ppdjax.sim.small_linalg import cholesky_solve


def _not_done(m, d, ctx) -> jax.Array:
  """MJX's while-loop predicate, without the iteration count."""
  improvement = solver._rescale(m, d, ctx.prev_cost - ctx.cost)  # pylint: disable=protected-access
  gradient = solver._rescale(m, d, math.norm(ctx.grad))  # pylint: disable=protected-access
  return (improvement >= m.opt.tolerance) & (gradient >= m.opt.tolerance)


def _update_gradient(m, d, ctx):
  """MJX's Newton gradient update (pyramidal cones) with the unrolled Cholesky solve."""
  grad = ctx.Ma - d.qfrc_smooth - ctx.qfrc_constraint
  efc_j = d._impl.efc_J  # pylint: disable=protected-access
  h = (efc_j.T * d._impl.efc_D * ctx.active) @ efc_j  # pylint: disable=protected-access
  h = support.full_m(m, d) + h
  return ctx.replace(grad=grad, Mgrad=cholesky_solve((h + h.T) * 0.5, grad))


def _iteration(m, d, ctx, unrolled_cholesky: bool):
  """One Newton iteration: MJX's loop body for solver="Newton"."""
  ctx = solver._linesearch(m, d, ctx)  # pylint: disable=protected-access
  ctx = solver._update_constraint(m, d, ctx)  # pylint: disable=protected-access
  if unrolled_cholesky:
    ctx = _update_gradient(m, d, ctx)
  else:
    ctx = solver._update_gradient(m, d, ctx)  # pylint: disable=protected-access
  return ctx.replace(search=-ctx.Mgrad, solver_niter=ctx.solver_niter + 1)


def solve(m, d, iterations: int, unrolled_cholesky: bool = True):
  """Constraint forces by `iterations` Newton steps (frozen once converged)."""
  qacc = d.qacc_smooth
  if not m.opt.disableflags & DisableBit.WARMSTART:
    warm = solver.Context.create(m, d.replace(qacc=d.qacc_warmstart), grad=False)
    smooth = solver.Context.create(m, d.replace(qacc=d.qacc_smooth), grad=False)
    qacc = jnp.where(warm.cost < smooth.cost, d.qacc_warmstart, d.qacc_smooth)
  d = d.replace(qacc=qacc)
  ctx = solver.Context.create(m, d)
  for _ in range(iterations):
    go = _not_done(m, d, ctx)
    # A converged element has a zero search direction; iterating it anyway (the result is
    # discarded) would put 0/0 into reverse-mode derivatives, so it searches along a
    # harmless unit direction instead.
    probe = ctx.replace(search=jnp.where(go, ctx.search, jnp.ones_like(ctx.search)))
    new = _iteration(m, d, probe, unrolled_cholesky)
    ctx = jax.tree.map(lambda a, b: jnp.where(go, a, b), new, ctx)
  return d.tree_replace({
      "qfrc_constraint": ctx.qfrc_constraint,
      "qacc": ctx.qacc,
      "_impl.efc_force": ctx.efc_force,
  })


def step(m, d, iterations: int, unrolled_cholesky: bool = True):
  """One Euler step of a JAX-backend MJX model with `iterations` Newton iterations."""
  if (m.opt.solver != SolverType.NEWTON or m.opt.integrator != IntegratorType.EULER
      or m.opt.cone != ConeType.PYRAMIDAL):
    raise ValueError("ppdjax's fixed-iteration step supports Newton, Euler and pyramidal "
                     "cones only")
  d = forward.fwd_position(m, d)
  d = forward.fwd_velocity(m, d)
  d = forward.fwd_actuation(m, d)
  d = forward.fwd_acceleration(m, d)
  if d._impl.efc_J.size == 0:  # pylint: disable=protected-access
    d = d.replace(qacc=d.qacc_smooth)
  else:
    d = solve(m, d, iterations, unrolled_cholesky)
  return forward.euler(m, d)
