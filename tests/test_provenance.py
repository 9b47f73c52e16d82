"""Provenance records (ppdjax.report.provenance) and the results index built from them."""

import dataclasses
import datetime
import json
import os
import platform
import shutil
import subprocess

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest
from flax import nnx

from ppdjax.report import index, provenance

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "experiments", "results")
CONFIG = {"model": {"width": 64, "boxes": [1, 2]}, "seed": 0}


@dataclasses.dataclass(frozen=True)
class _Model:
  width: int


@dataclasses.dataclass(frozen=True)
class _Config:
  model: _Model
  seed: int


class _Tiny(nnx.Module):

  def __init__(self, w):
    self.w = nnx.Param(jnp.asarray(w, jnp.float32))
    self.b = nnx.Param(jnp.zeros((2,), jnp.float32))
    self.rngs = nnx.Rngs(0)


def _result(folder, top1=31.5):
  path = os.path.join(folder, "results.json")
  with open(path, "w", encoding="utf-8") as f:
    json.dump({"table2": {"PPD+Sample": {"top1": top1, "ci95": {"top1": [30.0, 33.0]}},
                          "a/b": {"rmse": 4}}, "name": "x", "ok": True}, f)
  return path


def test_record_has_every_field(tmp_path):
  path = _result(tmp_path)
  weights = tmp_path / "weights"
  weights.mkdir()
  (weights / "w.npz").write_bytes(b"abc")
  record_file = provenance.write_provenance(
      path, command=["python", "-m", "ppdjax.evaluate", "--out=a b"], config=CONFIG,
      weights=str(weights), extra={"note": "test"},
      headlines={"top-1": "table2/PPD+Sample/top1", "top-1 high": "table2/PPD+Sample/ci95/top1/1",
                 "slashed key": "table2/a/b/rmse"})
  assert record_file == path + ".provenance.json"
  record = provenance.read_provenance(path)
  assert record == provenance.read_provenance(record_file)
  created = datetime.datetime.fromisoformat(record["created"])
  assert created.utcoffset() == datetime.timedelta(0)
  assert abs(datetime.datetime.now(datetime.timezone.utc) - created).total_seconds() < 600
  assert record["command"] == "python -m ppdjax.evaluate '--out=a b'"
  assert record["result"] == "results.json"
  head = subprocess.run(["git", "-C", ROOT, "rev-parse", "HEAD"], capture_output=True, text=True)
  assert record["commit"] == (head.stdout.strip() if head.returncode == 0 else None)
  assert isinstance(record["dirty"], bool) or record["commit"] is None
  versions = record["versions"]
  assert set(versions) == {"python", "jax", "jaxlib", "flax", "mujoco", "mujoco_mjx", "numpy",
                           "ppdjax"}
  assert versions["python"] == platform.python_version()
  assert versions["jax"] == jax.__version__ and versions["numpy"] == np.__version__
  assert all(versions.values())
  assert record["device"] == {"backend": jax.default_backend(),
                              "kind": jax.devices()[0].device_kind, "count": len(jax.devices())}
  assert len(record["config_hash"]) == 64
  assert record["weights_hash"] == provenance.weights_hash(str(weights))
  assert record["headlines"] == [
      {"name": "top-1", "key": "table2/PPD+Sample/top1", "value": 31.5},
      {"name": "top-1 high", "key": "table2/PPD+Sample/ci95/top1/1", "value": 33.0},
      {"name": "slashed key", "key": "table2/a/b/rmse", "value": 4}]
  assert record["extra"] == {"note": "test"}


def test_hashes_are_canonical_and_see_changes(tmp_path):
  same = {"seed": 0, "model": {"boxes": [1, 2], "width": 64}}  # another key order
  assert provenance.config_hash(CONFIG) == provenance.config_hash(same)
  assert provenance.config_hash(CONFIG) == provenance.config_hash(
      ml_collections.ConfigDict(CONFIG))
  assert provenance.config_hash(_Config(_Model(64), 0)) == provenance.config_hash(
      {"model": {"width": 64}, "seed": 0})
  assert provenance.config_hash({**CONFIG, "seed": 1}) != provenance.config_hash(CONFIG)
  assert provenance.config_hash(None) is None and provenance.weights_hash(None) is None

  a, b = _Tiny(np.arange(6.0).reshape(2, 3)), _Tiny(np.arange(6.0).reshape(2, 3))
  b.rngs()  # RNG counters are not weights
  assert provenance.weights_hash(a) == provenance.weights_hash(b)
  b.w.value = b.w.value.at[0, 0].set(1.0)
  assert provenance.weights_hash(a) != provenance.weights_hash(b)

  (tmp_path / "w" / "sub").mkdir(parents=True)
  (tmp_path / "w" / "a.npz").write_bytes(b"a")
  (tmp_path / "w" / "sub" / "b.npz").write_bytes(b"b")
  shutil.copytree(tmp_path / "w", tmp_path / "copy")
  assert provenance.weights_hash(tmp_path / "w") == provenance.weights_hash(tmp_path / "copy")
  (tmp_path / "copy" / "sub" / "b.npz").write_bytes(b"c")
  assert provenance.weights_hash(tmp_path / "w") != provenance.weights_hash(tmp_path / "copy")


def test_missing_or_non_numeric_key_raises_and_writes_nothing(tmp_path):
  path = _result(tmp_path)
  for key, what in [("table2/PPD/top1", "'PPD'"), ("table2/PPD+Sample/ci95/top1/2", "'2'"),
                    ("name", "'x'"), ("ok", "True")]:
    with pytest.raises(ValueError, match=what) as raised:
      provenance.write_provenance(path, command="c", headlines={"h": key})
    assert repr(key) in str(raised.value)
  assert not os.path.exists(path + ".provenance.json")


def test_folder_result_and_missing_git(tmp_path, monkeypatch):
  folder = tmp_path / "run"
  (folder / "test").mkdir(parents=True)
  _result(folder / "test")
  monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))  # no git: the record is still written
  record_file = provenance.write_provenance(folder, command="c",
                                            headlines={"t": "test/results.json/table2/a/b/rmse"})
  assert record_file == str(folder / "provenance.json")
  record = provenance.read_provenance(folder)
  assert record["commit"] is None and record["dirty"] is None
  assert record["headlines"][0]["value"] == 4
  assert provenance.result_of(record_file) == str(folder)


def test_index_lists_headlines_and_check_catches_changes(tmp_path):
  (tmp_path / "a").mkdir()
  path = _result(tmp_path / "a")
  provenance.write_provenance(path, command="python make.py --x=1",
                              headlines={"PPD+Sample top-1 (%)": "table2/PPD+Sample/top1"})
  assert index.check(str(tmp_path)) == [f"{tmp_path}/INDEX.md is not what "
                                        "`python -m ppdjax.report.index` generates: rerun it"]
  text = open(index.write(str(tmp_path)), encoding="utf-8").read()
  assert "## [a/results.json](a/results.json)" in text
  assert "python make.py --x=1" in text
  assert "| PPD+Sample top-1 (%) | 31.50 | `table2/PPD+Sample/top1` |" in text
  assert index.check(str(tmp_path)) == []
  _result(tmp_path / "a", top1=12.0)
  problems = index.check(str(tmp_path))
  assert len(problems) == 1 and "'PPD+Sample top-1 (%)'" in problems[0], problems
  assert "31.5" in problems[0] and "12.0" in problems[0]


def test_backfill_reads_the_file_and_its_commit(tmp_path):
  git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@example.com"]
  subprocess.run([*git, "init", "-q"], check=True)
  path = tmp_path / "bench.json"
  path.write_text(json.dumps({"meta": {"device": "NVIDIA H100 80GB HBM3", "jax": "0.11.2"},
                              "rows": [{"objects_per_s": 108.5}]}))
  subprocess.run([*git, "add", "bench.json"], check=True)
  subprocess.run([*git, "commit", "-q", "-m", "bench"], check=True)
  head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout
  provenance.backfill(str(path), headlines={"objects/s": "rows/0/objects_per_s"},
                      command="python bench.py")
  record = provenance.read_provenance(path)
  assert record["commit"] == head.strip() and record["dirty"] is False
  assert record["command"] == "python bench.py"
  assert record["versions"]["jax"] == "0.11.2" and record["versions"]["flax"] is None
  assert record["device"] == {"backend": None, "kind": "NVIDIA H100 80GB HBM3", "count": None}
  assert record["headlines"] == [{"name": "objects/s", "key": "rows/0/objects_per_s",
                                  "value": 108.5}]
  assert record["extra"]["backfilled"]


def test_repository_index_is_current_and_matches_its_files():
  assert index.find_records(RESULTS), "no provenance records under experiments/results"
  assert index.check(RESULTS) == []
