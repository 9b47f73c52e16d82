"""The PPD network, its targets and losses, box labels and metrics (no training here)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from ppdjax import box_overlap, metrics, primitives
from ppdjax.configs import tiny
from ppdjax.conventions import TIMESTEP
from ppdjax.nn import losses, model, motion, recurrent
from ppdjax.nn.resnet import ResNet18, load_torchvision_weights
from ppdjax.primitives import Primitives
from conftest import numpy_weights_model


def _obs(rng, b=3, t=24, hw=32):
  return {"voxels": jnp.asarray(rng.random((b, 32, 32, 32)) > 0.6, jnp.uint8),
          "image": jnp.asarray(rng.integers(0, 255, (b, hw, hw, 3)), jnp.uint8),
          "trajectories": jnp.asarray(rng.normal(size=(b, 4, t, 7)), jnp.float32)}


@pytest.fixture(scope="module")
def net():
  return model.init_module(lambda: model.PPD(tiny.get_config().model, rngs=nnx.Rngs(0)))


def _random_boxes(rng, b=4, k=5):
  q = rng.normal(size=(b, k, 4))
  return Primitives(jnp.asarray(rng.uniform(0.05, 0.4, (b, k, 3)), jnp.float32),
                    jnp.asarray(rng.uniform(-0.4, 0.4, (b, k, 3)), jnp.float32),
                    jnp.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True), jnp.float32),
                    jnp.asarray(rng.integers(1, 101, (b, k)) * 100.0, jnp.float32),
                    jnp.asarray(np.arange(k) < rng.integers(1, k + 1, (b, 1))))


@pytest.mark.slow  # ~13 s on 2 cores (eager passes): `make test-all`
def test_heads_stay_in_range(net, rng):
  obs = _obs(rng)
  prev = jnp.asarray(rng.normal(size=(3, 6, model.PRIM_DIM)) * 5, jnp.float32)
  for pred in (net(obs, prev, train=True, rngs=nnx.Rngs(dropout=0)), net.decode(obs)[1]):
    assert pred.density_logits.shape == (3, 6, 102)
    assert np.all((pred.half_size >= 0) & (pred.half_size <= 0.5))
    assert np.all(np.abs(pred.pos) <= 0.5)
    np.testing.assert_allclose(np.linalg.norm(pred.quat, axis=-1), 1.0, atol=1e-5)


def test_decoding_stops_at_the_end_token(rng):
  """Bias the density head towards END: one box (the first step always yields one);
  towards a slot: all five boxes; the slot is the box's density."""
  cfg = tiny.get_config().model
  cfg.use_image = cfg.use_voxels = False  # the generator alone decides; the encoders'
  net = numpy_weights_model(cfg, seed=1)
  obs = _obs(rng)
  decode = nnx.jit(lambda m, o: m.decode(o))  # compiled once: eager decoding is slower
  net.density_head.bias.value = jnp.zeros(102).at[model.END].set(100.0).at[41].set(50.0)
  prims, _ = decode(net, obs)
  assert prims.valid.tolist() == [[True, False, False, False, False]] * 3
  assert np.all(prims.density[:, 0] == 4200.0)
  net.density_head.bias.value = jnp.zeros(102).at[7].set(100.0)
  prims, _ = decode(net, obs)
  assert np.all(prims.valid) and np.all(prims.density == 800.0)


def test_ablation_switches_zero_a_feature(rng):
  obs = _obs(rng)
  encode = nnx.jit(lambda m, o: m.encode(o))  # one program per configuration, not op by op
  for switch in ("use_voxels", "use_image", "use_trajectory"):
    cfg = tiny.get_config().model
    cfg[switch] = False
    net = numpy_weights_model(cfg)
    f = encode(net, obs)
    assert f.shape == (3, cfg.feature) and np.all(np.isfinite(f)) and np.any(f != 0)
    changed = dict(obs)
    key = {"use_voxels": "voxels", "use_image": "image", "use_trajectory": "trajectories"}[switch]
    changed[key] = jnp.zeros_like(obs[key])
    np.testing.assert_array_equal(encode(net, changed), f)  # the ablated input is unused
    kept = "trajectories" if switch != "use_trajectory" else "image"
    changed = dict(obs)
    changed[kept] = jnp.zeros_like(obs[kept])
    assert not np.allclose(encode(net, changed), f)  # while an input it reads is used


def test_grouped_lstm_runs_independent_lstms(rng):
  lstm = recurrent.GroupedLSTM(3, 5, 8, rngs=nnx.Rngs(0))
  x = jnp.asarray(rng.normal(size=(2, 3, 7, 5)), jnp.float32)
  h = lstm(x)
  for g in range(3):
    c = hg = jnp.zeros((2, 8))
    for t in range(7):
      z = x[:, g, t] @ lstm.wx.value[g] + hg @ lstm.wh.value[g] + lstm.b.value[g]
      c, hg = recurrent._lstm_update(z, c)
    np.testing.assert_allclose(h[:, g], hg, atol=1e-5)


def test_trajectory_features_are_relative_and_compressed():
  traj = jnp.zeros((1, 1, 3, 7)).at[..., 3].set(1.0)
  traj = traj.at[0, 0, :, 0].set(jnp.array([2.0, 2.0 + 1 / 300, 2.0 + 2 / 300]))  # 1 m/s in x
  f = motion.trajectory_features(traj)
  np.testing.assert_allclose(f[0, 0, :, 0], [0, 1 / 300, 2 / 300], atol=1e-6)
  np.testing.assert_allclose(f[0, 0, 1:, 7], np.log1p(1.0 / motion.SPEED_SCALE), rtol=1e-3)


def test_conv_matches_xla_convolution(rng):
  conv = model.init_module(lambda: model.Conv3x3x3(2, 3, rngs=nnx.Rngs(0)))
  x = jnp.asarray(rng.normal(size=(2, 8, 8, 8, 2)), jnp.float32)
  ref = jax.lax.conv_general_dilated(x, conv.kernel.value, (1, 1, 1), "SAME",
                                     dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
  np.testing.assert_allclose(conv(x), ref + conv.bias.value, atol=1e-5)


def test_canonical_label_is_one_per_box(rng):
  """(s, q), (|G|ᵀ s, q ⊗ g) for the cube's rotations g, and (s, −q) get one label, the
  same solid (corners), and an axis-aligned box keeps its label."""
  boxes = _random_boxes(rng, 8)
  canon = primitives.canonical_boxes(boxes)
  for gi in rng.integers(0, 48, 6):
    g = jnp.asarray(primitives.BOX_SYMMETRIES[gi])
    perm = jnp.abs(primitives.quat_to_mat(g))
    other = boxes.replace(half_size=boxes.half_size @ perm,
                          quat=primitives.quat_mul(boxes.quat, g) * (-1) ** gi)
    again = primitives.canonical_boxes(other)
    np.testing.assert_allclose(again.quat, canon.quat, atol=1e-5)
    np.testing.assert_allclose(again.half_size, canon.half_size, atol=1e-5)
  assert np.all(canon.quat[..., 0] >= 0)
  key = lambda c: np.sort(np.round(np.asarray(c), 4).reshape(-1, 3), axis=0)
  np.testing.assert_allclose(key(primitives.corners(canon)), key(primitives.corners(boxes)),
                             atol=2e-4)
  aligned = boxes.replace(quat=jnp.zeros_like(boxes.quat).at[..., 0].set(1.0))
  same = primitives.canonical_boxes(aligned)
  np.testing.assert_array_equal(same.quat, aligned.quat)
  np.testing.assert_array_equal(same.half_size, aligned.half_size)


def test_targets_order_bottom_to_top_and_end(rng):
  boxes = _random_boxes(rng, 6)
  tgt = losses.targets(boxes)
  n = np.asarray(boxes.valid.sum(-1))
  ordered = np.asarray(primitives.bottom_to_top(boxes).pos)  # the rule: test_conventions
  for b in range(6):
    np.testing.assert_array_equal(np.asarray(tgt["pos"][b, :n[b]]), ordered[b, :n[b]])
    assert tgt["token"][b, n[b]] == model.END
    assert tgt["density_mask"][b].sum() == n[b] + 1
    assert tgt["geometry_mask"][b].sum() == n[b]
    assert np.all(tgt["token"][b, :n[b]] < 100)
    assert np.argmax(tgt["prev"][b, 0, :102]) == model.START
    np.testing.assert_array_equal(tgt["prev"][b, 1:n[b] + 1, 102:105], tgt["half_size"][b, :n[b]])


def test_loss_is_zero_for_the_truth_and_masks_padding(rng):
  boxes = _random_boxes(rng, 4)
  tgt = losses.targets(boxes)
  logits = jax.nn.one_hot(tgt["token"], 102) * 1e4
  pred = model.Prediction(logits, tgt["half_size"], tgt["pos"], tgt["quat"])
  loss, aux = losses.loss_fn(pred, tgt, 1.0)
  assert float(loss) < 1e-6
  noisy = pred.replace(half_size=jnp.where(tgt["geometry_mask"][..., None], pred.half_size,
                                           99.0))  # padding steps are ignored
  assert float(losses.loss_fn(noisy, tgt, 1.0)[0]) < 1e-6
  worse = pred.replace(pos=pred.pos + 0.1)
  n = float(boxes.valid.sum(-1).mean())
  np.testing.assert_allclose(losses.loss_fn(worse, tgt, 0.0)[1]["geometry_loss"], 0.3 * n,
                             rtol=1e-4)


def test_end_token_and_density_split_the_papers_cross_entropy(rng):
  """L_E + L_D is the paper's 102-way cross-entropy; with w = 0 only the end token learns."""
  boxes = _random_boxes(rng, 5)
  tgt = losses.targets(boxes)
  logits = jnp.asarray(rng.normal(size=(5, 6, 102)) * 3, jnp.float32)
  pred = model.Prediction(logits, tgt["half_size"], tgt["pos"], tgt["quat"])
  _, aux = losses.loss_fn(pred, tgt, 1.0)
  ce = optax.softmax_cross_entropy_with_integer_labels(logits, tgt["token"])
  paper = jnp.where(tgt["density_mask"], ce, 0.0).sum(-1).mean()
  np.testing.assert_allclose(aux["end_loss"] + aux["density_loss"], paper, rtol=1e-5)
  # with w = 0 the slots' scores do not matter (only how they weigh against the end
  # token): shuffling them leaves the loss as it is, and with w = 1 it does not
  shuffled = logits.at[..., :100].set(logits[..., :100][..., rng.permutation(100)])
  loss = lambda lg, w: float(losses.loss_fn(pred.replace(density_logits=lg), tgt, w)[0])
  assert loss(shuffled, 0.0) == pytest.approx(loss(logits, 0.0), rel=1e-6)
  assert loss(shuffled, 1.0) != pytest.approx(loss(logits, 1.0), rel=1e-3)
  grad = jax.grad(lambda lg: losses.loss_fn(pred.replace(density_logits=lg), tgt, 0.0)[0])
  assert float(jnp.abs(grad(logits)[..., model.END]).max()) > 1e-3  # the end token learns


def test_voxel_encoder_keeps_position_and_takes_voxels_alone(rng):
  config = tiny.get_config().model
  config.voxel_keep = 4
  obs = _obs(rng)
  # shapes only, traced (an eager build and encode take ~25 s on 2 cores)
  encode = lambda o: nnx.eval_shape(  # noqa: E731
      lambda: model.PPD(config, rngs=nnx.Rngs(0)).encode(o))
  f = encode({"voxels": obs["voxels"]})  # image and trajectories absent: zeros
  assert f.shape == (3, config.feature)
  assert encode({"voxels": obs["voxels"], "image": obs["image"] * 0,
                 "trajectories": obs["trajectories"]}).shape == f.shape
  config.voxel_keep = 3
  with pytest.raises(ValueError, match="voxel_keep"):
    model.PPD(config, rngs=nnx.Rngs(0))


def test_box_iou_against_exact_and_monte_carlo(rng):
  a = Primitives(jnp.array([0.2, 0.1, 0.3]), jnp.zeros(3), jnp.array([1.0, 0, 0, 0]), 1.0, True)
  b = Primitives(jnp.array([0.1, 0.1, 0.3]), jnp.array([0.15, 0.05, 0.1]),
                 jnp.array([1.0, 0, 0, 0]), 1.0, True)
  inter = 0.15 * 0.15 * 0.5
  exact = inter / (0.4 * 0.2 * 0.6 + 0.2 * 0.2 * 0.6 - inter)
  np.testing.assert_allclose(box_overlap.pair_iou(a, b), exact, atol=1e-3)
  np.testing.assert_allclose(box_overlap.pair_iou(a, a), 1.0, atol=1e-6)
  far = a.replace(pos=jnp.array([0.5, 0.0, 0.0]))  # disjoint: gap of 0.1 along x
  np.testing.assert_allclose(box_overlap.pair_iou(a, far), 0.0, atol=1e-6)
  for _ in range(3):  # rotated boxes against 10^6 random points
    boxes = _random_boxes(rng, 1, 2)
    x, y = jax.tree.map(lambda v: v[0, 0], boxes), jax.tree.map(lambda v: v[0, 1], boxes)
    y = y.replace(pos=x.pos + 0.3 * (y.pos - x.pos))
    pts = jnp.asarray(rng.uniform(-1, 1, (1_000_000, 3)), jnp.float32)
    ia, ib = box_overlap._inside(pts, x.half_size, x.pos, x.quat), box_overlap._inside(
        pts, y.half_size, y.pos, y.quat)
    mc = float((ia & ib).sum() / (ia | ib).sum())
    assert abs(float(box_overlap.pair_iou(x, y)) - mc) < 0.01


def test_shape_f1_and_density_metrics(rng):
  true = _random_boxes(rng, 1)
  true = true.replace(valid=jnp.array([[True, True, True, False, False]]),
                      pos=jnp.array([[[0, 0, -0.4], [0, 0, 0], [0, 0, 0.4]] + [[0, 0, 0]] * 2],
                                    jnp.float32),
                      half_size=jnp.full((1, 5, 3), 0.15), quat=jnp.zeros((1, 5, 4)).at[..., 0].set(1))
  pred = true.replace(pos=true.pos.at[0, 1, 0].add(0.2))  # one box moved off its match
  c = metrics.shape_counts(pred, true)
  assert int(c["matched"][0]) == 2
  assert metrics.f1_from_counts(**c) == pytest.approx(100 * 4 / 6)
  logits = jnp.zeros((1, 5, 100)).at[0, 0, 10].set(3).at[0, 1, 20].set(3).at[0, 1, 22].set(2)
  d = metrics.density_counts(logits, jnp.array([[10, 22, 50, 0, 0]]), true.valid)
  assert d["top1"][0] == 1 and d["top5"][0] == 2 and d["count"][0] == 3
  assert d["sq_err"][0] == 0 + 4 + 50 ** 2  # arg-max of an all-zero row is slot 0


def test_torchvision_weights_load_by_name(tmp_path, rng):
  """A state dict with torchvision's names and OIHW layouts (made here: no download)."""
  net = model.init_module(lambda: ResNet18(64, 64, rngs=nnx.Rngs(0)))
  sd = {}
  for path, v in nnx.to_flat_state(nnx.state(net)):
    names = [str(p) for p in path]
    if names[0] == "fc":
      continue
    leaf = {"kernel": "weight", "scale": "weight", "bias": "bias", "mean": "running_mean",
            "var": "running_var"}[names[-1]]
    shape = v.value.shape
    if names[-1] == "kernel":
      shape = (shape[3], shape[2], shape[0], shape[1])
    sd[".".join(names[:-1] + [leaf])] = rng.normal(size=shape).astype(np.float32)
  sd["fc.weight"] = np.zeros((1000, 512), np.float32)
  np.savez(tmp_path / "r18.npz", **sd)
  load_torchvision_weights(net, str(tmp_path / "r18.npz"))
  np.testing.assert_array_equal(net.conv1.kernel.value,
                                np.transpose(sd["conv1.weight"], (2, 3, 1, 0)))
  np.testing.assert_array_equal(net.layer2[0].downsample[1].var.value,
                                sd["layer2.0.downsample.1.running_var"])
  del sd["layer4.1.bn2.bias"]
  np.savez(tmp_path / "bad.npz", **sd)
  with pytest.raises(ValueError, match="99 of the 100"):
    load_torchvision_weights(net, str(tmp_path / "bad.npz"))
  with pytest.raises(ValueError, match="cannot read"):
    load_torchvision_weights(net, str(tmp_path / "missing.npz"))


def test_coordinate_channels_reach_the_voxel_feature():
  """With `coords`, the first convolution reads occupancy + 3 coordinate channels, and those
  channels change the feature of the same grid."""
  enc = model.init_module(
      lambda: model.VoxelEncoder(8, coords=True, rngs=nnx.Rngs(params=0)))
  kernel = enc.convs[0].kernel
  assert kernel.value.shape == (3, 3, 3, 4, 2)
  vox = np.zeros((1, 32, 32, 32), np.uint8)
  vox[0, 4:9, 10:20, 2:6] = 1
  forward = nnx.jit(lambda e, v: e(v, train=False))  # one program for both, not op by op
  with_coords = forward(enc, jnp.asarray(vox))
  kernel.value = kernel.value.at[:, :, :, 1:].set(0.0)
  assert with_coords.shape == (1, 8)
  assert not np.allclose(with_coords, forward(enc, jnp.asarray(vox)))


@pytest.mark.slow  # gradients of a second model configuration (~35 s on 2 cores); a model
# with the branch is still built in the default run (test_bad_files)
def test_density_branch_keeps_the_losses_apart(rng):
  """model.density_branch: the density loss moves neither the voxel encoder nor the
  geometry's LSTMs and heads; the geometry loss does not move the density branch."""
  cfg = tiny.get_config().model
  cfg.density_branch, cfg.dropout, cfg.use_image = True, 0.0, False  # no ResNet: faster
  cfg.early_motion_steps = 2
  net = model.PPD(cfg, rngs=nnx.Rngs(2))
  obs, tgt = _obs(rng), losses.targets(_random_boxes(rng, b=3))

  @nnx.jit
  def grads(m):  # compiled once for both terms: eager differentiation is far slower
    term = lambda name: lambda m: losses.loss_fn(m(obs, tgt["prev"]), tgt, 1.0)[1][name]
    return nnx.grad(term("density_loss"))(m), nnx.grad(term("geometry_loss"))(m)

  largest = lambda g: {k: max(float(jnp.abs(x).max()) for x in jax.tree.leaves(v))
                       for k, v in nnx.to_pure_dict(g).items()}
  density, geometry = map(largest, grads(net))
  for part in ("voxel_encoder", "fuse", "cells", "size_head", "trans_head", "rot_head"):
    assert density[part] == 0.0, part
  for part in ("density_fuse", "density_cells", "density_head", "trajectory_encoder"):
    assert density[part] > 0.0, part
  for part in ("density_fuse", "density_cells", "density_head"):
    assert geometry[part] == 0.0, part
  for part in ("voxel_encoder", "cells", "size_head"):
    assert geometry[part] > 0.0, part


def test_early_motion_reads_velocities_after_the_push():
  """A body moving at constant linear and angular velocity: every early-motion step holds
  them, compressed; the features follow the pushes' order; the branch needs a density branch."""
  dt, v, w = TIMESTEP, np.array([0.3, -0.2, 0.05]), np.array([0.0, 0.0, 1.5])
  t = np.arange(6)[:, None] * dt
  angle = w[2] * t[:, 0]
  quat = np.stack([np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)], -1)
  traj = np.concatenate([v * t, quat], -1)[None, None]  # (1, 1, 6, 7)
  rest = np.broadcast_to(np.r_[0.1, 0, 0.2, 1, 0, 0, 0], traj.shape)
  traj = np.concatenate([traj, rest], 1)  # push 2: at rest
  got = np.asarray(motion.early_motion(jnp.asarray(traj, jnp.float32), 3)).reshape(2, 3, 6)
  squash = lambda x: np.sign(x) * np.log1p(np.abs(x) / motion.SPEED_SCALE)
  np.testing.assert_allclose(got[0], np.tile(squash(np.r_[v, w]), (3, 1)), atol=2e-3)
  np.testing.assert_allclose(got[1], 0.0, atol=1e-4)
  cfg = tiny.get_config().model
  cfg.early_motion_steps = 4
  with pytest.raises(ValueError, match="density_branch"):
    model.PPD(cfg, rngs=nnx.Rngs(0))
