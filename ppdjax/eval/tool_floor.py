"""The realistic tools benchmark's floor: what a Bayes reader of the observations reads.

For a sample of test tools (configs/tools.py), a reader that knows the generator reads
each box's density by Bayes from the voxels and the trajectories: a reference for how far
the benchmark's labels can be read at all.

- **Geometry.** The builder's hidden dimensions (its uniform draws, `tools`) restricted to
  those whose normalised tool has exactly the observed voxels: a Metropolis-within-Gibbs
  chain redrawing one dimension at a time in its prior range, kept where the voxels still
  match. It starts at the tool's own dimensions, itself a posterior draw; a few samples of
  one chain spread less than the posterior, so the floor errs on the optimistic side.
- **Physics.** Trajectories depend on the densities through the body's mass properties θ
  (log mass, centre of mass, log second moments), tracked as a camera would (a frame every
  FRAME_STRIDE steps, SIGMA_POSITION / SIGMA_ROTATION of noise), linearised about the
  true θ by central differences of MuJoCo C rollouts: likelihood exp(-(θ - θ̂)ᵀ F (θ - θ̂)
  / 2), F = JᵀJ, θ̂ the truth plus one draw of the noise's effect N(0, F⁻¹).
- **Densities.** Each piece's prior is the generator's (a material uniformly from its
  part's plausible set, a slot uniformly in its range); every slot pair of the (<= 2)
  pieces is scored on every geometry sample; each box reads its piece's marginal mode
  (best top-1) or mean (best RMSE).

The image is unused (its edges could pin thicknesses the voxels cannot): the floor is what
voxels and motion identify. Offline NumPy and MuJoCo C.
"""

from __future__ import annotations

import numpy as np

from ppdjax.conventions import TIMESTEP, slot_to_density
from ppdjax.dataset import tool_scene, tools
from ppdjax.dataset.materials import material_slots
from ppdjax.dataset.meshes import normalize, voxelize_parts

FRAME_STRIDE = 10  # steps of 1/300 s between tracked frames: a 30 fps camera
SIGMA_POSITION = 1e-3  # m: the tracking noise of a frame's position
SIGMA_ROTATION = np.deg2rad(0.2)  # rad: ... and of its rotation
GEOMETRIES = 16  # geometry samples the densities are scored on
SWEEPS_BETWEEN = 3  # Gibbs sweeps over the dimensions between two kept samples
STEPS_FD = (0.02, 2e-3, 0.02)  # central differences: log mass; centre (m); log inertia
FD_RETRIES = 3


class _Recorder:
  """A NumPy Generator's stand-in that records the builder's draws (uniform: its range and
  value; choice: its value) so that a builder can be replayed with other dimensions."""

  def __init__(self, rng: np.random.Generator):
    self.rng, self.draws = rng, []

  def uniform(self, low=0.0, high=1.0):
    value = float(self.rng.uniform(low, high))
    self.draws.append(("uniform", float(low), float(high), value))
    return value

  def choice(self, options):
    value = self.rng.choice(options)
    self.draws.append(("choice", None, None, value))
    return value


class _Replay:
  """Plays recorded draws back, uniform values replaced by `values` (one per uniform)."""

  def __init__(self, draws, values):
    self.draws, self.values, self.i, self.u = draws, values, 0, 0

  def uniform(self, *_):
    self.i, self.u = self.i + 1, self.u + 1
    return float(self.values[self.u - 1])

  def choice(self, _):
    self.i += 1
    return self.draws[self.i - 1][3]


def builder_draws(seed: int, index: int) -> tuple[str, list]:
  """(category, the builder's recorded draws) of tool `index` of `seed`, as
  `tools.sample_tool` draws them (its geometry)."""
  rng = np.random.default_rng([seed, index])
  category = tools.CATEGORIES[rng.integers(len(tools.CATEGORIES))]
  recorder = _Recorder(rng)
  tools._BUILDERS[category](recorder)  # pylint: disable=protected-access
  return category, recorder.draws


def parts_of(category: str, draws, values) -> list:
  """The normalised parts of the builder replayed with uniform draws `values`."""
  built = tools._BUILDERS[category](_Replay(draws, values))  # pylint: disable=protected-access
  parts, _ = normalize([mesh for _, mesh, _ in built])
  return parts


def geometry_samples(category: str, draws, voxels: np.ndarray, count: int,
                     rng: np.random.Generator, sweeps: int = SWEEPS_BETWEEN) -> list:
  """`count` samples (each the normalised parts) of the geometries whose voxels are
  exactly `voxels`: a chain started at the recorded dimensions, each step redrawing one
  dimension uniformly in its prior range, kept where the voxels still match."""
  ranges = [(lo, hi) for kind, lo, hi, _ in draws if kind == "uniform"]
  values = np.asarray([v for kind, _, _, v in draws if kind == "uniform"], np.float64)
  out = []
  for _ in range(count):
    for _ in range(sweeps):
      for d in rng.permutation(len(ranges)):
        proposal = values.copy()
        proposal[d] = rng.uniform(*ranges[d])
        try:
          parts = parts_of(category, draws, proposal)
        except ValueError:  # a degenerate shape (no volume): outside the prior's support
          continue
        if np.array_equal(voxelize_parts(parts)[0], voxels):
          values = proposal
    out.append(parts_of(category, draws, values))
  return out


def piece_terms(parts, pieces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Per piece, per unit density: volume (Q,), first moment (Q, 3) and second-moment
  inertia about the origin (Q, 3, 3), summed over its parts."""
  q = max(pieces) + 1
  vol, first, inertia = np.zeros(q), np.zeros((q, 3)), np.zeros((q, 3, 3))
  for part, piece in zip(parts, pieces):
    part = part.copy()
    part.density = 1.0
    v, c = float(part.mass), np.asarray(part.center_mass)
    vol[piece] += v
    first[piece] += v * c
    inertia[piece] += part.moment_inertia + v * (c @ c * np.eye(3) - np.outer(c, c))
  return vol, first, inertia


_UPPER = np.triu_indices(3)


def _logm(a: np.ndarray, f=np.log) -> np.ndarray:
  """f of symmetric (..., 3, 3) (positive definite for the log): the matrix log or exp."""
  w, v = np.linalg.eigh(a)
  return np.einsum("...ij,...j,...kj->...ik", v, f(np.maximum(w, 1e-30) if f is np.log else w), v)


def thetas(terms, rho: np.ndarray) -> np.ndarray:
  """(N, 10) mass properties θ = (log mass, centre of mass (3), the matrix logarithm of the
  second moments about it per unit mass, Σ = tr(I)/2 - I (6: xx, xy, xz, yy, yz, zz): any
  θ is a body, its inertia positive and within the triangle inequality) of the pieces at
  densities rho (N, Q)."""
  vol, first, inertia = terms
  mass = rho @ vol
  com = (rho @ first) / mass[:, None]
  about_origin = np.einsum("nq,qij->nij", rho, inertia)
  shift = mass[:, None, None] * (np.einsum("ni,ni->n", com, com)[:, None, None] * np.eye(3)
                                 - np.einsum("ni,nj->nij", com, com))
  inertia = (about_origin - shift) / mass[:, None, None]
  spread = np.trace(inertia, axis1=1, axis2=2)[:, None, None] / 2 * np.eye(3) - inertia
  per_mass = _logm(spread)
  return np.concatenate([np.log(mass)[:, None], com, per_mass[:, _UPPER[0], _UPPER[1]]], 1)


def _inertial(theta: np.ndarray):
  """(mass, centre of mass, inertia about it) of one θ (`tool_scene.simulate_tool`)."""
  mass, log = float(np.exp(theta[0])), np.zeros((3, 3))
  log[_UPPER] = theta[4:]
  spread = _logm(log + np.triu(log, 1).T, np.exp)
  return mass, theta[1:4], (np.trace(spread) * np.eye(3) - spread) * mass


def track(traj: np.ndarray) -> np.ndarray:
  """What a camera reads of trajectories (P, T, 7), scaled by the noise: every
  FRAME_STRIDE-th frame's position / SIGMA_POSITION and rotation vector (from the rest
  pose) / SIGMA_ROTATION, flattened."""
  from scipy.spatial.transform import Rotation  # pylint: disable=import-outside-toplevel
  frames = traj[:, FRAME_STRIDE - 1::FRAME_STRIDE]
  rest = Rotation.from_quat(traj[:, :1, [4, 5, 6, 3]].reshape(-1, 4))
  rot = Rotation.from_quat(frames[..., [4, 5, 6, 3]].reshape(-1, 4))
  turned = (rot * Rotation.from_quat(np.repeat(rest.inv().as_quat(), frames.shape[1], 0))
            ).as_rotvec().reshape(frames.shape[:2] + (3,))
  return np.concatenate([(frames[..., :3] / SIGMA_POSITION).ravel(),
                         (turned / SIGMA_ROTATION).ravel()])


def information(parts, theta_obs: np.ndarray, pushes, steps: int) -> np.ndarray:
  """(10, 10) Fisher information of θ from the tracked trajectories (`track`) at θ_obs:
  Jᵀ J, J by central differences of MuJoCo C rollouts of the tool `parts` (a step whose
  rollout MuJoCo stops as unstable is halved, up to FD_RETRIES times)."""
  scale = np.asarray([STEPS_FD[0]] + [STEPS_FD[1]] * 3 + [STEPS_FD[2]] * 6)
  rollout = lambda theta: track(tool_scene.simulate_tool(  # noqa: E731
      parts, None, pushes, steps=steps, inertial=_inertial(theta)))
  columns = []
  for d in range(10):
    for attempt in range(FD_RETRIES + 1):
      e = np.zeros(10)
      e[d] = scale[d] / 2 ** attempt
      try:
        plus, minus = rollout(theta_obs + e), rollout(theta_obs - e)
        break
      except RuntimeError:
        if attempt == FD_RETRIES:
          raise
    columns.append((plus - minus) / (2 * e[d]))
  jac = np.stack(columns, 1)
  return jac.T @ jac


def slot_prior(materials: tuple[str, ...]) -> np.ndarray:
  """(100,) prior of one piece's slot: a material uniformly from `materials`, then a slot
  uniformly within its range."""
  prior = np.zeros(100)
  for m in materials:
    slots = material_slots(m)
    prior[slots] += 1.0 / (len(materials) * len(slots))
  return prior


def read_tool(geometries: list, pieces, piece_sets, theta_obs: np.ndarray, fisher: np.ndarray,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
  """(mode slots (Q,), posterior-mean slots (Q,)) of the pieces given the geometry samples
  and the information about θ; the noise's draw from `rng`."""
  cov = np.linalg.pinv(fisher)
  cov = 0.5 * (cov + cov.T)
  seen = rng.multivariate_normal(theta_obs, cov, method="eigh")
  priors = [slot_prior(s) for s in piece_sets]
  support = [np.flatnonzero(p) for p in priors]
  grid = np.stack(np.meshgrid(*support, indexing="ij"), -1).reshape(-1, len(support))
  rho = slot_to_density(grid)
  log_prior = sum(np.log(priors[q][grid[:, q]]) for q in range(len(support)))
  logpost = []
  for parts in geometries:
    diff = thetas(piece_terms(parts, pieces), rho) - seen
    logpost.append(-0.5 * np.einsum("ni,ij,nj->n", diff, fisher, diff) + log_prior)
  logpost = np.stack(logpost)  # (G, N): geometries weigh alike (the chain's samples)
  weight = np.exp(logpost - logpost.max())
  weight = weight.sum(0) / weight.sum()
  mode, mean = [], []
  for q in range(len(support)):
    marginal = np.bincount(grid[:, q], weight, minlength=100)
    mode.append(int(np.argmax(marginal)))
    mean.append(float(marginal @ np.arange(100)))
  return np.asarray(mode), np.asarray(mean)


def piece_sets(tool: tools.Tool) -> list[tuple[str, ...]]:
  """Each piece's plausible materials (`tools.PLAUSIBLE_MATERIALS`), in piece order."""
  by_name = {n: m for names, m in tools.PLAUSIBLE_MATERIALS[tool.category] for n in names}
  first = {}
  for name, piece in zip(tool.names, tool.pieces):
    first.setdefault(piece, by_name[name])
  return [first[q] for q in range(tool.num_pieces)]


def read_test_tool(data, seed: int, index: int, configs: int, geometries: int,
                   chain_seed: int, steps: int) -> dict:
  """The floor's reading of tool `index` of `seed` under its first `configs` density
  configurations, as the dataset labels its boxes: per box (valid, with a part) the true
  slot, the posterior mode's and mean's slots, the material, the part's thickness."""
  from ppdjax.dataset import tool_generation  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset.mesh_boxes import boxes_of_parts  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng([chain_seed, seed, index])
  tool = tools.sample_plausible_tool(seed, index)
  category, draws = builder_draws(seed, index)
  parts, _ = normalize(list(tool.parts))
  voxels = voxelize_parts(parts)[0]
  pushes = tool_generation.tool_pushes(data, parts)
  _, owner = boxes_of_parts(parts, tool.densities)
  samples = geometry_samples(category, draws, voxels, geometries, rng)
  sets = piece_sets(tool)
  pieces = np.asarray(tool.pieces)
  terms = piece_terms(parts, tool.pieces)
  thick = tools.part_thicknesses(parts)
  out = {k: [] for k in ("true", "mode", "mean", "material", "thickness", "config")}
  for c, variant in enumerate(tool_generation.density_variants(tool, seed, index, configs)):
    first_part = [int(np.flatnonzero(pieces == q)[0]) for q in range(tool.num_pieces)]
    rho = variant.densities[first_part]
    theta_obs = thetas(terms, rho[None])[0]
    fisher = information(parts, theta_obs, pushes, steps)
    mode, mean = read_tool(samples, tool.pieces, sets, theta_obs, fisher, rng)
    for o in owner[owner >= 0]:
      q = pieces[o]
      out["true"].append(int(variant.slots[o]))
      out["mode"].append(int(mode[q]))
      out["mean"].append(float(mean[q]))
      out["material"].append(variant.materials[o])
      out["thickness"].append(float(thick[o]))
      out["config"].append(c)
  return {"index": index, "category": category, **out}


def _read(args):
  """`read_test_tool`, or None where MuJoCo C stops its rollouts (the data draws another)."""
  try:
    return read_test_tool(*args)
  except RuntimeError:
    return None


def compute(config, workers: int = 0, progress: bool = True) -> dict:
  """The floor of the realistic tools preset `config` (its `floor` section): its first
  `floor.tools` test tools (the dataset's split of `config.seed`), each under its first
  `floor.configs` density configurations; top-1 and RMSE of the posterior's mode, RMSE
  of its mean, over boxes, with the same by material; in `workers` processes."""
  from tqdm import tqdm  # pylint: disable=import-outside-toplevel
  from ppdjax.dataset import storage, tool_generation  # pylint: disable=import-outside-toplevel
  data, f = config.data, config.floor
  if tool_generation.materials_mode(data) != "plausible":
    raise ValueError("the floor reads the realistic benchmark's labels "
                     "(data.tool_materials = 'plausible')")
  ids = np.arange(data.num_tools)
  test = ids[storage.split_of(ids, tuple(data.split_fractions)) == storage.SPLITS["test"]]
  jobs = [(data, int(config.seed), int(i), min(f.configs, data.configs_per_tool),
           f.geometries, f.seed, data.steps) for i in test[:f.tools]]
  with tool_generation.ToolWorkers(workers) as pool:
    read = list(tqdm(pool.imap(jobs, _read), total=len(jobs), desc="floor", unit="tool",
                     disable=not progress))
  rows = [r for r in read if r is not None]
  return {**summarize(rows, config), "unstable_tools": len(read) - len(rows)}


def intervals(per_tool: list) -> dict:
  """95 % bootstrap intervals of the mode's top-1 and RMSE over boxes, resampling whole
  tools (their boxes and configurations share a shape): {"top1": [lo, hi], "rmse": ...}."""
  from ppdjax.metrics import bootstrap_interval  # pylint: disable=import-outside-toplevel
  true = np.concatenate([np.asarray(r["true"]) for r in per_tool])
  mode = np.concatenate([np.asarray(r["mode"]) for r in per_tool])
  tool = np.concatenate([np.full(len(r["true"]), k) for k, r in enumerate(per_tool)])
  top1 = lambda i: 100.0 * float(np.mean(true[i] == mode[i]))  # noqa: E731
  rmse = lambda i: float(np.sqrt(np.mean((true[i] - mode[i]) ** 2)))  # noqa: E731
  return {name: list(bootstrap_interval(f, len(true), groups=tool))
          for name, f in (("top1", top1), ("rmse", rmse))}


def summarize(rows: list, config) -> dict:
  """The floor's scores over every box of `rows` (`read_test_tool`'s)."""
  cat = lambda k: np.concatenate([np.asarray(r[k]) for r in rows])  # noqa: E731
  true, mode, mean, material = cat("true"), cat("mode"), cat("mean"), cat("material")
  score = lambda m: {"boxes": int(m.sum()), "top1": 100.0 * float(np.mean(mode[m] == true[m])),
                     "rmse": float(np.sqrt(np.mean((mode[m] - true[m]) ** 2))),
                     "rmse_mean": float(np.sqrt(np.mean((mean[m] - true[m]) ** 2)))}
  every = np.ones(len(true), bool)
  return {**score(every), "by_material": {m: score(material == m) for m in np.unique(material)},
          "tools": len(rows), "objects": int(sum(len(set(r["config"])) for r in rows)),
          "reader": {"frame_seconds": FRAME_STRIDE * TIMESTEP,
                     "sigma_position_m": SIGMA_POSITION,
                     "sigma_rotation_deg": float(np.rad2deg(SIGMA_ROTATION)),
                     "geometries": int(config.floor.geometries), "uses_image": False},
          "per_tool": [{"index": r["index"], "category": r["category"],
                        "true": r["true"], "mode": r["mode"]} for r in rows],
          "ci95": intervals(rows)}
