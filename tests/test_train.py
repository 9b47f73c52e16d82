"""Training: the tiny preset, overfitting, exact resume, 8 fake devices, loading, errors."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from ppdjax import load, metrics
from ppdjax.configs import tiny
from ppdjax.conventions import OBS_KEYS
from ppdjax.dataset import batching, storage
from ppdjax.training import checkpoints, loader, loop
from ppdjax.training import state as train_state

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def short_config(geometry_steps=3, joint_steps=3, stream_steps=0):
  """A few steps of the tiny preset; with stream_steps, geometry-stream steps first and the
  stream's loss kept on beside the dataset's afterwards."""
  config = tiny.get_config()
  config.train.update(geometry_steps=geometry_steps, joint_steps=joint_steps, log_every=1,
                      eval_every=1000, eval_batches=1, stream_steps=stream_steps,
                      stream_weight=0.5 if stream_steps else 0.0)
  return config


def _run_on_fake_devices(code: str, devices: int, timeout: int) -> None:
  """Runs `code` in a second Python process on `devices` forced CPU devices (JAX fixes its
  device count when it starts), sharing the compilation cache; fails with its stderr."""
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
             JAX_COMPILATION_CACHE_DIR=os.path.join(ROOT, ".jax_cache"))
  done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env,
                        capture_output=True, text=True, timeout=timeout)
  assert done.returncode == 0, done.stderr[-3000:]


STREAM = 2  # geometry-stream steps of the stream-phase test


def _rows(workdir, split="train"):
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    rows = [json.loads(line) for line in f]
  return [r for r in rows if r.get("split", "train") == split]


def _params(workdir):
  model, _ = load(workdir, "latest")
  return jax.tree.leaves(nnx.state(model))


def _interrupted_at(stop: int, config, data: str, workdir: str, monkeypatch) -> None:
  """Trains until step `stop` and interrupts it there (Ctrl-C: the loop saves)."""
  real = train_state.Trainer.train_step

  def interrupt(self, batch, step, w):
    if step == stop:
      raise KeyboardInterrupt
    return real(self, batch, step, w)

  monkeypatch.setattr(train_state.Trainer, "train_step", interrupt)
  with pytest.raises(KeyboardInterrupt):
    loop.train_and_evaluate(config, data, workdir, progress=False)
  monkeypatch.setattr(train_state.Trainer, "train_step", real)


@pytest.fixture(scope="module")
def straight_run(tiny_dataset, tmp_path_factory):
  workdir = str(tmp_path_factory.mktemp("straight"))
  loop.train_and_evaluate(short_config(), tiny_dataset, workdir, progress=False)
  return workdir


@pytest.mark.slow  # two more compilations (~45 s on 2 cores): `make test-all`
def test_stream_phase_then_dataset_phases_and_exact_resume(tiny_dataset, tmp_path, monkeypatch):
  """Stream steps first, then the dataset's phases with the stream's loss beside them;
  interrupted inside the stream phase and run again, the run is bitwise the same."""
  straight, resumed = str(tmp_path / "straight"), str(tmp_path / "resumed")
  loop.train_and_evaluate(short_config(stream_steps=STREAM), tiny_dataset, straight,
                           progress=False)
  rows = _rows(straight)
  assert [r["phase"] for r in rows] == [0, 0, 1, 1, 1, 2, 2, 2]
  assert "density_loss" not in rows[0] and "end_loss" in rows[0]  # placeholder densities
  assert all("stream_geometry_loss" in r for r in rows[2:])
  _interrupted_at(2, short_config(stream_steps=STREAM), tiny_dataset, resumed, monkeypatch)
  loop.train_and_evaluate(short_config(stream_steps=STREAM), tiny_dataset, resumed,
                           progress=False)
  key = lambda rows: [(r["step"], r["loss"], r["geometry_loss"]) for r in rows]
  assert key(_rows(resumed)) == key(rows)
  for a, b in zip(_params(resumed), _params(straight), strict=True):
    np.testing.assert_array_equal(a, b)


def test_tiny_preset_trains_with_a_falling_loss(tiny_run):
  workdir, final = tiny_run
  rows = _rows(workdir)
  config = tiny.get_config().train
  assert rows[-1]["step"] == config.geometry_steps + config.joint_steps
  first = [r["geometry_loss"] for r in rows[:2]]
  last = [r["geometry_loss"] for r in rows[-2:]]
  assert np.mean(last) < 0.8 * np.mean(first)  # 0.72 after the 60 steps
  phase2 = [r["density_loss"] for r in rows if r["phase"] == 2]
  assert np.mean(phase2[-2:]) < np.mean(phase2[:2])
  val = _rows(workdir, "val")
  assert val and set(val[-1]) >= {"step", "loss", "density_top1", "density_rmse", "shape_f1"}
  assert final == {k: v for k, v in val[-1].items() if k not in ("step", "split")}
  for name in ("config.json", "learning_curve.png", "checkpoints", "best", "tensorboard"):
    assert os.path.exists(os.path.join(workdir, name)), name
  assert any(f.startswith("events.out.tfevents")
             for f in os.listdir(os.path.join(workdir, "tensorboard")))


def test_load_returns_the_trained_model(tiny_run, tiny_dataset):
  workdir, final = tiny_run
  # a finished run, run again, trains nothing and reports its last validation
  assert loop.train_and_evaluate(tiny.get_config(), tiny_dataset, workdir,
                                  progress=False) == final
  model, config = load(workdir)
  assert config.train.batch_size == tiny.get_config().train.batch_size
  sample = storage.open_dataset(tiny_dataset, "test")[0]
  obs = {k: jnp.asarray(sample[k])[None] for k in OBS_KEYS}
  prims, raw = nnx.jit(lambda m, o: m.decode(o))(model, obs)
  assert prims.density.shape == (1, 5) and bool(prims.valid[0, 0])
  with pytest.raises(checkpoints.CheckpointError, match="config.json is missing"):
    load(os.path.dirname(workdir))


@pytest.mark.slow  # about 2.5 minutes on 2 cores: run with `make test-all`
def test_overfits_sixteen_samples(tiny_dataset):
  """Geometry loss near zero and density top-1 above 90% on the 16 samples it saw."""
  config = tiny.get_config()
  config.model.dropout = 0.0
  config.train.learning_rate = 3e-3
  ds = storage.open_dataset(tiny_dataset, "train")
  batch = jax.tree.map(jnp.asarray, loader.model_inputs(next(batching.batches(ds, 16, seed=0))))
  graphdef, state = nnx.split(train_state.build(config))
  t, weights = config.train, train_state.loss_weights(config.train)
  step = jax.jit(lambda s, b, i: train_state.train_step(graphdef, s, b, i, 0.5, t))
  evaluate = jax.jit(lambda s, b: train_state.eval_step(graphdef, s, b, 0.5, weights))
  first, _ = evaluate(state, batch)
  for i in range(300):
    state, _ = step(state, batch, i)
  aux, counts = evaluate(state, batch)
  summary = metrics.summarize(counts)
  boxes = int(batch["primitives"].valid.sum())
  # L_G sums 10 coordinates per box over a sample's boxes: per coordinate < 1 cm
  assert float(aux["geometry_loss"]) / (10 * boxes / 16) < 0.01, aux
  assert float(aux["geometry_loss"]) < 0.15 * float(first["geometry_loss"])
  assert summary["top1"] > 90, summary


@pytest.mark.slow  # a second training and its compilation (~55 s on 2 cores): `make test-all`;
# test_load_returns_the_trained_model resumes a finished run in the default tests
def test_resume_is_bitwise_equal(straight_run, tiny_dataset, tmp_path, monkeypatch):
  """Interrupted at step 4 (Ctrl-C: it saves), run again: identical losses and weights."""
  workdir = str(tmp_path / "resumed")
  _interrupted_at(4, short_config(), tiny_dataset, workdir, monkeypatch)
  assert [r["step"] for r in _rows(workdir)] == [1, 2, 3, 4]
  loop.train_and_evaluate(short_config(), tiny_dataset, workdir, progress=False)
  key = lambda rows: [(r["step"], r["loss"], r["geometry_loss"], r.get("density_loss"))
                      for r in rows]
  assert key(_rows(workdir)) == key(_rows(straight_run))
  for a, b in zip(_params(workdir), _params(straight_run), strict=True):
    np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # a cross-check of ~55 s on 2 cores (a second process compiles): `make test-all`
def test_eight_fake_devices_match_one(straight_run, tiny_dataset, tmp_path):
  workdir = str(tmp_path / "eight")
  code = ("import jax; from ppdjax.training import loop; "
          "from tests.test_train import short_config; assert jax.device_count() == 8; "
          f"loop.train_and_evaluate(short_config(), {tiny_dataset!r}, "
          f"{workdir!r}, "
          "progress=False)")
  _run_on_fake_devices(code, 8, timeout=900)
  one, eight = _rows(straight_run), _rows(workdir)
  assert [r["step"] for r in eight] == [r["step"] for r in one]
  for a, b in zip(one, eight):
    np.testing.assert_allclose(b["loss"], a["loss"], rtol=1e-4)


@pytest.mark.slow  # two compilations in a second process, about a minute on 2 cores
def test_per_device_batch_norm_averages_each_devices_step(tiny_dataset):
  """train.batch_norm = "per_device" over 2 devices: the logged loss, the BatchNorm
  running statistics and Adam's first moment (linear in the gradient) are the means of
  one-device steps on each half of the batch."""
  code = f"""
import jax, jax.numpy as jnp, numpy as np, tempfile
from flax import nnx
from ppdjax.dataset import batching, storage
from ppdjax.training import loader, state as ts
from tests.test_train import short_config
config = short_config()
config.model.dropout = 0.0
config.train.update(batch_size=8, batch_norm="per_device")
ds = storage.open_dataset({tiny_dataset!r}, "train")
batch = jax.tree.map(jnp.asarray, loader.model_inputs(next(batching.batches(ds, 8, seed=0))))
graphdef, state = nnx.split(ts.build(config))
halves = []
for half in (slice(0, 4), slice(4, 8)):
  one = config.copy_and_resolve_references()
  one.train.batch_size = 4
  step = jax.jit(lambda s, b: ts.train_step(graphdef, s, b, 0, 0.5, one.train))
  halves.append(step(jax.tree.map(jnp.copy, state), jax.tree.map(lambda x: x[half], batch)))
with tempfile.TemporaryDirectory() as workdir:
  trainer = ts.Trainer(config, workdir)
  aux = trainer.train_step(batch, 0, 0.5)
  both = jax.tree.map(np.asarray, trainer.state)
np.testing.assert_allclose(aux["geometry_loss"],
                           np.mean([h[1]["geometry_loss"] for h in halves]), rtol=1e-5)
np.testing.assert_allclose(aux["density_loss"],
                           np.mean([h[1]["density_loss"] for h in halves]), rtol=1e-5)
pick = lambda tree, kind: jax.tree.leaves(nnx.State(tree).filter(kind))
stats = [pick(h[0]["model"], nnx.BatchStat) for h in halves]
assert stats[0]
for got, a, b in zip(pick(both["model"], nnx.BatchStat), *stats, strict=True):
  np.testing.assert_allclose(got, (np.asarray(a) + np.asarray(b)) / 2, rtol=1e-4, atol=1e-6)
mu = lambda tree: [x for p, x in jax.tree_util.tree_leaves_with_path(tree["optimizer"])
                   if "mu" in jax.tree_util.keystr(p)]
for got, a, b in zip(mu(both), mu(halves[0][0]), mu(halves[1][0]), strict=True):
  np.testing.assert_allclose(got, (np.asarray(a) + np.asarray(b)) / 2, rtol=1e-4, atol=1e-7)
"""
  _run_on_fake_devices(code, 2, timeout=900)


def test_a_subset_of_the_devices_takes_the_work():
  """`devices=` keeps training and per-object work on the devices named (the peer of
  experiments/benchmarks/bench_devices.py), and all local devices are the default; either compiles
  ahead of time from shapes alone."""
  code = f"""
import jax, jax.numpy as jnp, numpy as np, pytest
from ppdjax.training import sharding
d0, d1 = jax.devices()
f = lambda a, b: a * b.sum()
one = sharding.jit_over_local_devices(f, replicated=(1,), devices=[d1])(jnp.arange(4.0),
                                                                       jnp.ones(3))
assert one.devices() == {{d1}}, one.devices()
both = sharding.jit_over_local_devices(f, replicated=(1,))(jnp.arange(4.0), jnp.ones(3))
assert both.devices() == {{d0, d1}}, both.devices()
np.testing.assert_array_equal(one, both)
# ahead of time, from shapes alone (Evaluator.compile(execute=False)), on a device and on both
shapes = (jax.ShapeDtypeStruct((4,), jnp.float32), jax.ShapeDtypeStruct((3,), jnp.float32))
for devices in ([d1], None):
  compiled = sharding.jit_over_local_devices(f, replicated=(1,), devices=devices).lower(
      *shapes).compile()
  np.testing.assert_array_equal(compiled(jnp.arange(4.0), jnp.ones(3)), one)
with pytest.raises(ValueError, match="multiple of 2"):
  sharding.jit_over_local_devices(f, replicated=(1,))(jnp.arange(3.0), jnp.ones(3))
assert sharding.check_batch_size(3, devices=1) == 3
with pytest.raises(ValueError, match="multiple of the 2 devices"):
  sharding.check_batch_size(3)
# Trainer(devices=) builds its mesh so (a Trainer costs ~13 s to build here)
assert list(sharding.make_mesh([d1]).devices) == [d1] and sharding.make_mesh().size == 2
placed = jax.device_put(jnp.ones(4), sharding.replicated(sharding.make_mesh([d1])))
assert placed.devices() == {{d1}}
"""
  _run_on_fake_devices(code, 2, timeout=300)


def test_bad_configs_and_inputs_are_named(tiny_dataset, straight_run, tmp_path, monkeypatch):
  for section, key, value, match in [("train", "batch_size", 0, "batch_size"),
                                     ("model", "dropout", 1.0, "dropout"),
                                     ("train", "joint_steps", -1, "joint_steps"),
                                     ("train", "batch_norm", "sync", "batch_norm")]:
    config = short_config()
    config[section][key] = value
    with pytest.raises(ValueError, match=match):
      loop.check_config(config)
  config = short_config()
  config.model.use_voxels = False
  config.train.stream_steps = 2
  with pytest.raises(ValueError, match="use_voxels=False"):
    loop.check_config(config)
  config = short_config()
  config.train.init_from = str(tmp_path / "nowhere")
  with pytest.raises(ValueError, match="init_from"):
    loop.check_config(config)
  config = short_config()
  config.model.hidden = 32
  with pytest.raises(ValueError, match="model.hidden"):
    loop.train_and_evaluate(config, tiny_dataset, straight_run, progress=False)
  with pytest.raises(storage.DatasetError, match="no dataset"):
    loop.train_and_evaluate(short_config(), str(tmp_path / "none"), str(tmp_path / "w"))
  monkeypatch.setattr(jax, "device_count", lambda: 3)
  with pytest.raises(ValueError, match="multiple of the 3 devices"):
    loop.train_and_evaluate(short_config(), tiny_dataset, str(tmp_path / "w3"))


@pytest.mark.slow  # ~15 s on 2 cores: `make test-all`
def test_time_limit_stops_with_a_checkpoint_and_resumes(straight_run, tiny_dataset, tmp_path):
  """A call with no time left trains one step and saves it; the next call finishes the run
  exactly as an uninterrupted one."""
  workdir = str(tmp_path / "limited")
  config = short_config()
  loop.train_and_evaluate(config, tiny_dataset, workdir, progress=False, time_limit_s=0.0)
  assert loop.trained_steps(workdir) == 1
  loop.train_and_evaluate(config, tiny_dataset, workdir, progress=False)
  assert loop.trained_steps(workdir) == 6
  key = lambda rows: [(r["step"], r["loss"]) for r in rows]
  assert key(_rows(workdir)) == key(_rows(straight_run))


@pytest.mark.slow  # waits for the tiny run and builds two models (~40 s on 2 cores); the
# config checks of init_from stay in the default run (test_bad_configs_and_inputs_are_named)
def test_init_from_copies_what_matches(tiny_run):
  workdir, _ = tiny_run
  source, _ = load(workdir, "latest")
  config = tiny.get_config()
  config.model.voxel_keep = 4  # another voxel head: the rest still matches
  fresh = train_state.build(config).model
  with pytest.warns(UserWarning, match=r"start fresh: .*voxel_encoder/head1/kernel"):
    copied = train_state.init_from(fresh, workdir)
  assert any(p.startswith("voxel_encoder/convs") for p in copied)
  assert "voxel_encoder/head1/kernel" not in copied  # a 1x1x1 conv there, a dense layer here
  np.testing.assert_array_equal(fresh.voxel_encoder.convs[0].kernel.value,
                                source.voxel_encoder.convs[0].kernel.value)
  np.testing.assert_array_equal(fresh.density_head.kernel.value,
                                source.density_head.kernel.value)


def test_cosine_schedule_and_bad_schedule():
  t = tiny.get_config().train
  assert train_state.learning_rate(t) == t.learning_rate
  t.schedule = "cosine"
  rate = train_state.learning_rate(t)
  total = t.geometry_steps + t.joint_steps
  assert float(rate(0)) == pytest.approx(t.learning_rate)
  assert float(rate(total // 2)) == pytest.approx(t.learning_rate / 2, rel=1e-3)
  assert float(rate(total)) == pytest.approx(0.0, abs=1e-9)
  t.warmup_steps = 20  # a linear rise to the peak, then the cosine
  rate = train_state.learning_rate(t)
  assert float(rate(0)) == 0.0
  assert float(rate(10)) == pytest.approx(t.learning_rate / 2, rel=1e-3)
  assert float(rate(20)) == pytest.approx(t.learning_rate, rel=1e-3)
  assert float(rate(total)) == pytest.approx(0.0, abs=1e-9)
  t.warmup_steps = total
  with pytest.raises(ValueError, match="warmup_steps"):
    train_state.learning_rate(t)
  t.warmup_steps = 0
  t.schedule = "linear"
  with pytest.raises(ValueError, match="schedule"):
    train_state.learning_rate(t)


def test_density_weight_is_zero_before_the_joint_phase_and_ramps_in_it():
  t = tiny.get_config().train
  t.stream_steps, t.geometry_steps, t.joint_steps, t.density_weight = 3, 5, 10, 0.5
  first = t.stream_steps + t.geometry_steps  # the joint phase's first step
  assert [train_state.density_weight(t, s) for s in range(first)] == [0.0] * first
  assert train_state.density_weight(t, first) == 0.5  # no ramp: at once, as the paper
  t.density_ramp_steps = 4
  assert [train_state.density_weight(t, first + i) for i in range(6)] == pytest.approx(
      [0.125, 0.25, 0.375, 0.5, 0.5, 0.5])
  assert train_state.density_weight(t, first - 1) == 0.0
  t.density_ramp_steps = -1
  with pytest.raises(ValueError, match="density_ramp_steps"):
    loop.check_config(_with_train(t))


def _with_train(t):
  config = tiny.get_config()
  config.train = t
  return config


@pytest.mark.slow  # compiles a train step of its own (~20 s on 2 cores): `make test-all`
def test_clipping_bounds_the_first_update():
  """With train.clip_norm = 1, Adam's moments see the gradient rescaled to norm 1 (a 1e6
  gradient unclipped would put 1e5 into the first moment); its first step is ±rate."""
  config = tiny.get_config()
  config.train.clip_norm = 1.0
  ts = train_state.build(config)
  grads = jax.tree.map(lambda p: jnp.full_like(p, 1e6), nnx.state(ts.model, nnx.Param))
  before = jax.tree.leaves(nnx.state(ts.model, nnx.Param))
  # one compiled update: op by op, Adam over every parameter takes half a minute on a CPU
  nnx.jit(lambda optimizer, model, g: optimizer.update(model, g))(ts.optimizer, ts.model, grads)
  after = jax.tree.leaves(nnx.state(ts.model, nnx.Param))
  step = max(float(jnp.abs(a - b).max()) for a, b in zip(after, before))
  assert step == pytest.approx(config.train.learning_rate, rel=1e-3)
  m = jax.tree.leaves(ts.optimizer.opt_state)
  assert max(float(jnp.abs(x).max()) for x in m if jnp.issubdtype(x.dtype, jnp.floating)) < 1.0


def test_export_round_trip_and_corruption(tiny_run, tiny_dataset, tmp_path):
  """An exported model loads like the workdir (float16 weights), in files under the limit;
  a damaged or missing weights file is named."""
  workdir, _ = tiny_run
  out = str(tmp_path / "exported")
  with pytest.raises(ValueError, match="alone takes"):
    checkpoints.export(workdir, out, max_file_mb=0.1)
  record = checkpoints.export(workdir, out, max_file_mb=0.5)
  assert len(record["files"]) > 1
  assert all(f["bytes"] <= 0.5 * 2 ** 20 for f in record["files"])
  (a, _), (b, config) = load(workdir), load(out)
  assert config.model.to_dict() == tiny.get_config().model.to_dict()
  for x, y in zip(jax.tree.leaves(nnx.state(a)), jax.tree.leaves(nnx.state(b)), strict=True):
    assert y.dtype == x.dtype
    np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=2e-3, atol=2e-4)
  sample = storage.open_dataset(tiny_dataset, "test")[0]
  obs = {k: jnp.asarray(sample[k])[None] for k in OBS_KEYS}
  decode = nnx.jit(lambda m, o: m.decode(o)[1].density_logits)
  np.testing.assert_allclose(decode(b, obs), decode(a, obs), atol=0.05)
  path = os.path.join(out, record["files"][0]["name"])
  with open(path, "r+b") as f:
    f.seek(100)
    f.write(b"\0\0\0\0")
  with pytest.raises(checkpoints.CheckpointError, match="corrupt"):
    load(out)
  os.remove(path)
  with pytest.raises(checkpoints.CheckpointError, match="missing"):
    load(out)


@pytest.mark.slow  # ~20 s on 2 cores; test_export_round_trip_and_corruption pins corrupt files
def test_a_truncated_checkpoint_is_named_and_training_resumes_from_an_intact_one(
    tiny_dataset, tmp_path, capsys):
  config = short_config(joint_steps=5)
  config.train.eval_every = 2  # checkpoints at steps 4, 6, 8 are kept
  workdir = str(tmp_path / "run")
  loop.train_and_evaluate(config, tiny_dataset, workdir, progress=False)
  model_dir = os.path.join(workdir, checkpoints.LATEST, "8", "model")
  files = [os.path.join(d, f) for d, _, fs in os.walk(model_dir) for f in fs]
  victim = max(files, key=os.path.getsize)
  with open(victim, "r+b") as f:  # a crash in the middle of writing the newest step
    f.truncate(os.path.getsize(victim) // 2)
  with pytest.raises(checkpoints.CheckpointError, match="checkpoint step 8 in .* is unreadable"):
    load(workdir, "latest")
  capsys.readouterr()
  config.train.joint_steps = 7  # a resumable change: train on to step 10
  loop.train_and_evaluate(config, tiny_dataset, workdir, progress=False)
  out = capsys.readouterr().out
  assert "step 8" in out and "resuming from step 6" in out, out
  assert loop.trained_steps(workdir) == 10
  assert os.path.isdir(os.path.join(workdir, checkpoints.UNREADABLE, "8"))
  assert [r["step"] for r in _rows(workdir)] == list(range(1, 11))
  load(workdir, "latest")


@pytest.mark.slow  # two more compilations (~20 s on 2 cores): `make test-all`
def test_a_geometry_stream_run_reads_no_dataset_and_validates_on_a_held_out_stream(tmp_path):
  """The pipeline's geometry stage starts before the dataset exists: a run of stream steps
  alone opens no split and reports the held-out stream's geometry metrics."""
  config = short_config(geometry_steps=0, joint_steps=0, stream_steps=2)
  config.model.use_image = config.model.use_trajectory = False
  config.train.batch_size = 4
  final = loop.train_and_evaluate(config, str(tmp_path / "no_dataset_here"),
                                  str(tmp_path / "run"), progress=False)
  assert 0.0 <= final["shape_f1"] <= 100.0 and np.isfinite(final["geometry_loss"])
  assert _rows(str(tmp_path / "run"), "val")[-1]["step"] == 2
  assert not os.path.exists(tmp_path / "no_dataset_here")


def test_physics_stream_is_refused_where_it_cannot_serve():
  """Its fresh towers are the blocks' under the paper's pushes: a tools dataset or a model
  that reads no motion is named."""
  for change, message in ((lambda c: c.data.update(kind="tools"), "data.kind 'towers'"),
                          (lambda c: c.model.update(use_trajectory=False), "use_trajectory"),
                          (lambda c: c.train.update(physics_stream_weight=-1.0), ">= 0")):
    config = short_config()
    config.train.physics_stream_weight = 0.5
    change(config)
    with pytest.raises(ValueError, match=message):
      loop.check_config(config)


@pytest.mark.slow  # compiles a training step with a simulation inside (minutes on 2 cores)
def test_physics_stream_joins_the_loss_with_fresh_simulated_towers(tiny_dataset, tmp_path):
  """With train.physics_stream_weight, each step adds the loss of simulated fresh towers
  (no image), logged as physics_density_loss; the stream's batch is a function of its key:
  voxels by the dataset's rule, the simulation of its own boxes."""
  from ppdjax.dataset import physics_stream, stream  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.pushes import default_pushes  # pylint: disable=import-outside-toplevel
  from ppdjax.sim.rollout_mjx import DEFAULT_SETTINGS  # pylint: disable=import-outside-toplevel
  config = short_config(geometry_steps=1, joint_steps=2)
  config.train.physics_stream_weight = 0.5
  loop.train_and_evaluate(config, tiny_dataset, str(tmp_path), progress=False)
  rows = _rows(str(tmp_path))
  assert all(np.isfinite(r["physics_density_loss"]) for r in rows)
  make = lambda: physics_stream.training_batch(  # noqa: E731
      jax.random.key(5), 3, steps=8, pushes=default_pushes(), settings=DEFAULT_SETTINGS)
  a, b = make(), make()
  assert set(a) == {"voxels", "trajectories", "primitives"}  # no image: the model reads 0
  np.testing.assert_array_equal(a["trajectories"], b["trajectories"])
  np.testing.assert_array_equal(a["voxels"],
                                stream.voxelize_axis_aligned(a["primitives"]).astype(np.uint8))
  assert a["trajectories"].shape == (3, 4, 8, 7) and np.all(np.isfinite(a["trajectories"]))
