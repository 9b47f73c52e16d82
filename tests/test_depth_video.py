"""The RGB-D row: depth videos of pushed objects, the encoder that reads them, and the model
variant trained, evaluated and called through the one pipeline."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from conftest import numpy_weights_model
from ppdjax import primitives
from ppdjax.configs import tiny
from ppdjax.conventions import DEPTH_VIDEO, STEPS
from ppdjax.dataset import depth_video
from ppdjax.dataset.depth import FAR, render_depth
from ppdjax.sim.scene import rest_position

SIZE = 32


def _one_box(half, pos=(0.0, 0.0, 0.0)):
  return primitives.make(np.array([half]), np.array([pos]))


def _batch(prims):
  return jax.tree.map(lambda x: jnp.asarray(x)[None], prims)


def _still(prims, pushes=2):
  """Trajectories (P, T, 7) of an object that stays at rest."""
  traj = np.zeros((pushes, STEPS, 7), np.float32)
  traj[..., :3], traj[..., 3] = np.asarray(rest_position(prims)), 1.0
  return traj


def test_a_frame_at_rest_is_the_depth_camera_image():
  prims = primitives.make(np.array([[0.2, 0.1, 0.15], [0.1, 0.1, 0.2]]),
                          np.array([[0.0, 0.0, -0.15], [0.05, 0.0, 0.2]]))
  video = depth_video.depth_videos(_batch(prims), jnp.asarray(_still(prims))[None], 3, SIZE)
  assert video.shape == (1, 2, 3, SIZE, SIZE)
  ref = np.asarray(render_depth(prims, depth_video.video_camera(SIZE)))
  assert (ref < FAR).all() and (ref < 4.0).sum() > 50  # the object is in view
  np.testing.assert_allclose(np.asarray(video[0]), np.broadcast_to(ref, video.shape[1:]),
                             atol=1e-4)


def test_a_frame_shows_the_box_where_the_pose_puts_it():
  """A pose turning the object a quarter about z and moving it: the frame equals the
  depth camera's image of the box with its x and y sizes swapped, moved, axis-aligned."""
  prims = _one_box((0.3, 0.1, 0.2))
  traj = _still(prims, pushes=1)
  s = np.sin(np.pi / 4)
  traj[0, -1, :3] += (0.2, 0.1, 0.0)
  traj[0, -1, 3:] = (s, 0.0, 0.0, s)  # 90 degrees about z
  video = np.asarray(depth_video.depth_videos(_batch(prims), jnp.asarray(traj)[None], 2, SIZE))
  turned = _one_box((0.1, 0.3, 0.2), (0.2, 0.1, 0.0))
  cam = depth_video.video_camera(SIZE)
  np.testing.assert_allclose(video[0, 0, 0], np.asarray(render_depth(prims, cam)), atol=1e-4)
  np.testing.assert_allclose(video[0, 0, 1], np.asarray(render_depth(turned, cam)), atol=1e-4)
  assert np.abs(video[0, 0, 1] - video[0, 0, 0]).max() > 0.1


def test_frames_span_the_trajectory_and_bad_counts_are_named():
  steps = depth_video.frame_steps(16)
  assert steps[0] == 0 and steps[-1] == STEPS - 1 and len(set(steps.tolist())) == 16
  with pytest.raises(ValueError, match="video_frames"):
    depth_video.frame_steps(1)
  batch = {"trajectories": np.zeros((1, 4, STEPS, 7))}
  assert depth_video.with_depth_video(batch, None) is batch  # a model that reads none
  assert depth_video.with_depth_video({"voxels": 0}, (4, 16)) == {"voxels": 0}  # stream


def _rgbd_config():
  c = tiny.get_config()
  c.model.physics_input, c.model.video_frames, c.model.video_size = "depth_video", 4, 16
  return c


def test_the_rgbd_model_reads_the_motion_and_learns_from_it():
  config = _rgbd_config()
  config.model.use_voxels = config.model.use_image = False  # the video encoder alone
  net = numpy_weights_model(config.model)  # no random draw compiled per weight shape
  assert net.video == (4, 16) and net.physics_key == DEPTH_VIDEO
  prims = _one_box((0.3, 0.1, 0.2))
  still = _still(prims, pushes=4)
  moved = still.copy()
  moved[:, :, 0] += np.linspace(0.0, 0.4, STEPS)  # slides along x
  videos = depth_video.depth_videos(jax.tree.map(lambda x: jnp.stack([jnp.asarray(x)] * 2),
                                                 prims), jnp.asarray(np.stack([still, moved])),
                                    4, 16)
  obs = {DEPTH_VIDEO: videos}
  f_t = nnx.jit(lambda m: m._encoder_features(obs, False, None)[2])(net)
  assert float(jnp.abs(f_t[0] - f_t[1]).max()) > 1e-4  # the two motions read apart
  grads = nnx.jit(nnx.grad(lambda m: jnp.sum(m._encoder_features(obs, False, None)[2] ** 2)))(
      net)
  conv = grads.trajectory_encoder.convs[0].kernel.value
  assert float(jnp.abs(conv).max()) > 0  # the loss reaches the frames' convolutions


def test_bad_depth_videos_and_settings_are_named():
  from ppdjax.infer.decompose import check_observation
  from ppdjax.reproduce.blocks_common import VARIANTS, variant_config
  from ppdjax.report.tables import PAPER_TABLE2
  from ppdjax.training.loop import check_config
  config = _rgbd_config()
  obs = {"voxels": np.zeros((32, 32, 32), np.uint8), "image": np.zeros((64, 64, 3), np.uint8),
         "trajectories": _still(_one_box((0.3, 0.1, 0.2)), pushes=4)}
  with pytest.raises(ValueError, match="lacks 'depth_video'"):
    check_observation(obs, config)
  with pytest.raises(ValueError, match=r"expected shape \(4, 4, 16, 16\)"):
    check_observation({**obs, DEPTH_VIDEO: np.full((4, 2, 16, 16), 3.0)}, config)
  for bad in (np.nan, 0.0, -1.0):
    video = np.full((4, 4, 16, 16), 3.0, np.float32)
    video[0, 0, 0, 0] = bad
    with pytest.raises(ValueError, match="finite and > 0"):
      check_observation({**obs, DEPTH_VIDEO: video}, config)
  assert check_observation({**obs, DEPTH_VIDEO: np.full((4, 4, 16, 16), 3.0)}, config) is False
  for key, value, match in (("physics_input", "rgbd", "physics_input"),
                            ("video_size", 24, "video_size"),
                            ("video_frames", 1, "video_frames")):
    bad = _rgbd_config()
    bad.model[key] = value
    with pytest.raises(ValueError, match=match):
      check_config(bad)
  rgbd = variant_config(tiny.get_config(), "rgbd")
  assert rgbd.model.physics_input == "depth_video" and VARIANTS["rgbd"][1] in PAPER_TABLE2


@pytest.mark.slow
def test_the_rgbd_variant_trains_evaluates_and_decomposes(tiny_dataset, tmp_path):
  """The pipeline's RGB-D row on the tiny data: videos made in the training step and the
  evaluation's batches; `make_decompose_fn` asks the user for them."""
  import ppdjax
  from ppdjax import open_dataset
  from ppdjax.eval import evaluation
  from ppdjax.reproduce.blocks_common import NETWORK_ONLY
  from ppdjax.training import loop
  config = _rgbd_config()
  config.train.geometry_steps, config.train.joint_steps, config.train.eval_every = 2, 4, 3
  workdir = str(tmp_path / "rgbd")
  final = loop.train_and_evaluate(config, tiny_dataset, workdir, progress=False)
  assert np.isfinite(final["loss"])
  settings = evaluation.eval_settings(config, **NETWORK_ONLY)
  result = evaluation.evaluate(workdir, tiny_dataset, settings, max_objects=4)
  assert result["objects"] == 4 and np.isfinite(result["table2"]["PPD"]["rmse"])
  sample = open_dataset(tiny_dataset, "test")[0]
  obs = {k: sample[k] for k in ("voxels", "image", "trajectories")}
  fn = ppdjax.make_decompose_fn(workdir)
  with pytest.raises(ValueError, match="depth_video"):
    fn(obs, jax.random.key(0))
  one = jax.tree.map(lambda x: np.asarray(x)[None], sample["primitives"])
  obs[DEPTH_VIDEO] = np.asarray(depth_video.depth_videos(one, sample["trajectories"][None],
                                                         4, 16)[0])
  got = fn(obs, jax.random.key(0)).primitives
  assert got.density.shape[-1] == 5 and np.isfinite(np.asarray(got.density)).all()
