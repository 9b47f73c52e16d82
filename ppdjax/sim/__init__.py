"""Physics: the scene, mass properties, pushes, and rollouts in MJX (jitted) or MuJoCo C."""

import contextlib
import io

# MJX prints "Failed to import warp" on first import when its optional Warp backend is
# absent (ppdjax does not use it): import it once here, quietly.
with contextlib.redirect_stdout(io.StringIO()):
  from mujoco import mjx  # noqa: F401
