"""The shipped block-tower model and example tower (assets/) load and decompose."""

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import ppdjax
from ppdjax import data, metrics

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "experiments"))
import decompose_example  # noqa: E402

MODEL = os.path.join(ROOT, "assets", "blocks_model")
EXAMPLE = os.path.join(ROOT, "assets", "blocks_example.npz")


def test_shipped_files_are_within_the_size_limits():
  sizes = [os.path.getsize(os.path.join(MODEL, f)) for f in os.listdir(MODEL)]
  assert max(sizes) <= 16 * 2 ** 20 and sum(sizes) <= 50 * 2 ** 20


def test_shipped_model_recovers_the_example_tower():
  model, config = ppdjax.load(MODEL)
  assert config.name == "paper" and config.model.resnet_width == 64
  obs, true = decompose_example.load_example(EXAMPLE)
  assert obs["image"].shape == (224, 224, 3) and int(true.valid.sum()) == 4
  batch = {k: jnp.asarray(v)[None] for k, v in obs.items()}
  prims, _ = nnx.jit(lambda m, o: m.decode(o))(model, batch)
  assert int(prims.valid.sum()) == 4
  true_b = jax.tree.map(lambda x: jnp.asarray(x)[None], true)
  assert int(metrics.match_boxes(prims, true_b)[0]) >= 3  # boxes with IoU > 0.5


def test_a_broken_example_file_is_named(tmp_path):
  bad = tmp_path / "bad.npz"
  bad.write_bytes(b"not a zip")
  with pytest.raises(data.DatasetError, match="not a readable example"):
    decompose_example.load_example(str(bad))
  np.savez(tmp_path / "partial.npz", voxels=np.zeros((32, 32, 32), np.uint8))
  with pytest.raises(data.DatasetError, match="not a readable example"):
    decompose_example.load_example(str(tmp_path / "partial.npz"))
