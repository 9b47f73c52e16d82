"""`simulate`: every object under every push from rest, in MJX (jitted) or MuJoCo C."""

from __future__ import annotations

import jax
import numpy as np

from ppdjax.conventions import MAX_DENSITY, MIN_DENSITY, STEPS
from ppdjax.primitives import Primitives, check
from ppdjax.sim import rollout_mjx, rollout_mujoco
from ppdjax.sim.box_plane import BoxPlaneSettings
from ppdjax.sim.pushes import Pushes, default_pushes

BACKENDS = ("mjx", "box_plane", "mujoco")


def _is_traced(prims: Primitives) -> bool:
  return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(prims))


def simulate(prims: Primitives, pushes: Pushes | None = None, *, steps: int = STEPS,
             backend: str = "mjx", **options) -> jax.Array:
  """Rolls out every object under every push from rest.

  Args:
    prims: Primitives with leading batch axes B... (fields (B..., K, ...)).
    pushes: Pushes (P of them); None for the paper's four.
    steps: recorded steps of 1/300 s.
    backend: "mjx" (jitted, batched MJX; differentiable in forward mode), "box_plane"
      (the same contact model in a step written for one body of boxes on a plane, with
      MuJoCo C's box-plane contacts: faster, and differentiable in both modes; see
      `ppdjax.sim.box_plane`) or "mujoco" (MuJoCo's C engine on all CPU cores: the
      reference, and the fast path on a CPU).
    **options: backend settings: `settings=` a `ppdjax.sim.rollout_mjx.MjxSettings`
      ("mjx") or a `ppdjax.sim.box_plane.BoxPlaneSettings` ("box_plane"); for "mujoco"
      see `ppdjax.sim.rollout_mujoco.simulate`.

  Returns:
    (B..., P, steps, 7) object-frame poses after each step; float32 for "mjx" and "box_plane",
    float64 for "mujoco". In the JAX engines a rollout that leaves the scene (farther than
    `rollout_mjx.ESCAPE_DISTANCE` from the origin) keeps its last pose inside.

  Raises:
    ValueError: malformed boxes or pushes (`Primitives.validate`), or a valid box's density
      outside [MIN_DENSITY, MAX_DENSITY] = [100, 10,000] kg/m^3 (concrete inputs): the
      range the engines are stable in on the paper's pushes (the density classes). Lighter
      boxes fly off and the solvers diverge: a tower of 30 kg/m^3 or less blows up in
      MuJoCo C (docs/physics.md).
    rollout_mujoco.UnstableRollout: MuJoCo C stopped a rollout on a warning, naming it.
    FloatingPointError: a JAX engine's rollout that is not finite (concrete inputs).
  """
  if backend not in BACKENDS:
    raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
  if not isinstance(steps, (int, np.integer)) or steps < 1:
    raise ValueError(f"steps must be a positive int, got {steps!r}")
  pushes = default_pushes() if pushes is None else pushes
  if not isinstance(pushes, Pushes):
    raise TypeError(f"pushes: expected ppdjax.Pushes or None, got {type(pushes).__name__}")
  check(prims)
  if not _is_traced(prims):
    density = np.asarray(prims.density)[np.asarray(prims.valid)]
    # float32 exp(log(10,000)) is 10,000.001: refinement's densities reach the ends so
    outside = (density < MIN_DENSITY * (1 - 1e-6)) | (density > MAX_DENSITY * (1 + 1e-6))
    if outside.any():
      raise ValueError(
          f"Primitives.density: valid boxes' densities must lie in [{MIN_DENSITY:g}, "
          f"{MAX_DENSITY:g}] kg/m^3, where the engines are stable under the paper's pushes; "
          f"got {np.unique(density[outside]).tolist()[:5]}")
  if not _is_traced(pushes):
    pushes.validate()
  if backend == "mjx":
    if not isinstance(options.get("settings", rollout_mjx.MjxSettings()), rollout_mjx.MjxSettings):
      raise ValueError('backend="mjx" takes settings=MjxSettings(...)')
    return _finite(rollout_mjx.simulate(prims, pushes, steps=steps, **options), prims)
  if backend == "box_plane":
    settings = options.pop("settings", BoxPlaneSettings())
    if options or not isinstance(settings, BoxPlaneSettings):
      raise ValueError('backend="box_plane" takes only settings=BoxPlaneSettings(...)')
    return _finite(rollout_mjx.simulate(prims, pushes, steps=steps, settings=settings), prims)
  if _is_traced(prims):
    raise ValueError('backend="mujoco" runs on concrete arrays; it cannot be traced by jit')
  return rollout_mujoco.simulate(prims, pushes, steps=steps, **options)


def _finite(traj: jax.Array, prims: Primitives) -> jax.Array:
  """`traj`, checked to be finite where it is concrete."""
  if _is_traced(prims) or isinstance(traj, jax.core.Tracer):
    return traj
  ok = np.asarray(jax.numpy.isfinite(traj).all(axis=(-2, -1)))  # (B..., P)
  if not ok.all():
    where = tuple(int(x) for x in np.argwhere(~ok)[0])
    raise FloatingPointError(f"the rollout of object {where[:-1]} under push {where[-1]} is "
                             "not finite: the simulation diverged")
  return traj
