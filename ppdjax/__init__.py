"""ppdjax: Physical Primitive Decomposition in JAX, with MuJoCo MJX physics.

The public API, re-exported from the subpackages that follow the data flow:
primitives -> sim (physics) -> dataset -> nn (network) -> training -> infer (decompose) ->
eval (the tables) -> report.
"""

import os

# MuJoCo picks its OpenGL platform when it is first imported: headless EGL unless the
# user chose otherwise (rendering needs it; physics does not).
os.environ.setdefault("MUJOCO_GL", "egl")

# pylint: disable=wrong-import-position
from ppdjax.primitives import Primitives  # noqa: E402
from ppdjax.sim.mass import MassProperties, mass_properties  # noqa: E402
from ppdjax.sim.pushes import Pushes, default_pushes  # noqa: E402
from ppdjax.sim.simulate import simulate  # noqa: E402
from ppdjax.dataset.towers import sample_towers  # noqa: E402
from ppdjax.dataset.voxels import voxelize  # noqa: E402
from ppdjax.dataset.storage import open_dataset  # noqa: E402
from ppdjax.dataset.mesh_files import load_object  # noqa: E402
from ppdjax.dataset.mesh_boxes import primitives_from_mesh  # noqa: E402
from ppdjax.training.checkpoints import load  # noqa: E402
from ppdjax.infer.fit import fit_boxes  # noqa: E402
from ppdjax.infer.config import DecomposeConfig  # noqa: E402
from ppdjax.infer.decompose import make_decompose_fn  # noqa: E402
from ppdjax.infer.active import candidate_pushes, make_next_push_fn  # noqa: E402

__all__ = ["Primitives", "MassProperties", "mass_properties", "Pushes", "default_pushes",
           "simulate", "sample_towers", "voxelize", "open_dataset", "load_object",
           "primitives_from_mesh", "load",
           "fit_boxes", "DecomposeConfig", "make_decompose_fn", "candidate_pushes",
           "make_next_push_fn"]
__version__ = "0.1.0"
