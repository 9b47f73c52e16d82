"""Test setup: CPU backend, JAX's persistent compilation cache, shared fixtures."""

import contextlib
import fcntl
import json
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The suite is bound by compilation on a CPU: LLVM's expensive passes cost more compile time
# than they save in run time here (MJX's rollouts compiled in 29 s instead of 39 and ran as
# fast; the results are the same programs, so every bound holds).
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                           " --xla_llvm_disable_expensive_passes=true").strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

_CACHE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".jax_cache")
jax.config.update("jax_compilation_cache_dir", _CACHE)
# every program, however quick to compile: the two workers and the modules compile many of
# the same small ones
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def index(tree, i):
  """The i-th object of a batched pytree."""
  return jax.tree.map(lambda x: x[i], tree)


def face_errors(fit, truth):
  """(boxes, 6) metres: |face - true face| of each true box, both taken bottom to top."""
  from ppdjax.primitives import bottom_to_top  # pylint: disable=import-outside-toplevel
  faces = lambda p: (lambda q: np.concatenate([q.pos - q.half_size, q.pos + q.half_size], -1))(
      jax.tree.map(np.asarray, bottom_to_top(jax.tree.map(jax.numpy.asarray, p))))
  return np.abs(faces(fit) - faces(truth))[np.asarray(truth.valid)]


CLIS = ("ppdjax.decompose", "ppdjax.evaluate")  # the command lines tests import in-process


def cli_module(name: str):
  """The command-line module `name` (one of CLIS), imported in this process with its flags.
  absl's flags are global, and these modules share flag names (--out): whichever other one
  a test of this worker imported first is forgotten, flags and module, and imported again
  by the next test that asks for it."""
  import importlib  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  import ppdjax  # pylint: disable=import-outside-toplevel
  from absl import flags  # pylint: disable=import-outside-toplevel
  for other in CLIS:
    if other != name and other in sys.modules:
      # its own flags and the --config its import defined through configs.cli
      for module in (other, "ppdjax.configs.cli"):
        for flag in flags.FLAGS.get_flags_for_module(module):
          delattr(flags.FLAGS, flag.name)
      del sys.modules[other]
      delattr(ppdjax, other.rsplit(".", 1)[1])
  return importlib.import_module(name)


SHARED_RUN = ("tiny_dataset", "tiny_run")  # made once per test run (below)
MAKES_SHARED_RUN = "test_evaluation.py"  # its first test needs the run: it makes it


def pytest_collection_modifyitems(config, items):
  """The modules' order, which `make test`'s two workers (taking whole modules, in this
  order) follow: first the module that makes the tiny dataset and run (the longest
  fixture), then the modules that never read them, then those that do, so that neither
  worker idles on the run's lock. Within each group, modules of more tests first (as
  pytest-xdist orders them by default)."""
  del config
  module = lambda item: item.nodeid.split("::")[0]  # noqa: E731
  counts, reads = {}, {}
  for item in items:
    m = module(item)
    counts[m] = counts.get(m, 0) + 1
    reads[m] = reads.get(m, False) or any(f in item.fixturenames for f in SHARED_RUN)
  group = lambda m: 0 if m.endswith(MAKES_SHARED_RUN) else (2 if reads[m] else 1)  # noqa: E731
  order = {m: i for i, m in enumerate(sorted(counts, key=lambda m: (group(m), -counts[m], m)))}
  items.sort(key=lambda item: order[module(item)])  # stable: tests keep their order


@pytest.fixture(scope="session")
def rng():
  return np.random.default_rng(1234)


@contextlib.contextmanager
def _made_once(tmp_path_factory, name):
  """(folder, made): a folder shared by every pytest-xdist worker of this run, and whether
  an earlier worker already filled it. The first worker to ask fills it under a file lock
  while the others wait, so the tiny dataset and run are made once, not once per worker."""
  base = tmp_path_factory.getbasetemp()
  root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
  folder, done = root / name, root / f"{name}.done"
  with open(root / f"{name}.lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
      yield str(folder), done.exists()
      done.touch()
    finally:
      fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
  """The tiny preset's dataset, generated once per test run (as `make demo` makes it)."""
  from ppdjax.configs import tiny
  from ppdjax.dataset import generation
  with _made_once(tmp_path_factory, "tiny_blocks") as (out, made):
    if not made:
      generation.generate(tiny.get_config(), out, progress=False)
  return out


@pytest.fixture(scope="session")
def tiny_run(tiny_dataset, tmp_path_factory):
  """The tiny preset trained exactly as the README's demo trains it, once per test run:
  (workdir, final). Tests read the workdir and never write to it."""
  from ppdjax.configs import tiny
  from ppdjax.training import loop
  with _made_once(tmp_path_factory, "tiny_run") as (workdir, made):
    final_file = workdir + ".final.json"
    if not made:
      final = loop.train_and_evaluate(tiny.get_config(), tiny_dataset, workdir, progress=False)
      with open(final_file, "w") as f:
        json.dump(final, f, default=float)
    with open(final_file) as f:
      final = json.load(f)
  return workdir, final


def numpy_weights_model(cfg, seed=0):
  """A PPD of `cfg` whose weights are drawn by NumPy (small normals; BatchNorm's statistics
  0 and 1): a model's structure without compiling one random draw per weight shape, which
  is most of an eager build's time on a CPU."""
  from flax import nnx  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from ppdjax.nn.model import PPD  # pylint: disable=import-outside-toplevel
  graphdef, state = nnx.split(nnx.eval_shape(lambda: PPD(cfg, rngs=nnx.Rngs(0))))
  gen = np.random.default_rng(seed)
  def fill(path, leaf):
    name = [getattr(k, "key", None) for k in path if hasattr(k, "key")][-1]
    if not jnp.issubdtype(leaf.dtype, jnp.floating):
      return jnp.zeros(leaf.shape, leaf.dtype)
    if name == "var":
      return jnp.ones(leaf.shape, leaf.dtype)
    if name == "mean":
      return jnp.zeros(leaf.shape, leaf.dtype)
    return jnp.asarray(gen.normal(0.0, 0.1, leaf.shape), leaf.dtype)
  return nnx.merge(graphdef, jax.tree_util.tree_map_with_path(fill, state))

