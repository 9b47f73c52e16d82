"""The video study's evaluate step: every test tower decomposed from its tracked and its
true trajectory, with and without refinement (`ppdjax.reproduce video`; the report reads
the files, `video_report`)."""

from __future__ import annotations

import jax
import numpy as np
from tqdm.auto import tqdm

from ppdjax import primitives
from ppdjax.conventions import slot_to_density
from ppdjax.dataset import camera, generation
from ppdjax.infer import sampling
from ppdjax.infer.config import DecomposeConfig
from ppdjax.infer.decompose import make_decompose_fn
from ppdjax.training import checkpoints

WAYS = ("tracked", "true")  # which trajectory the model reads


def decompose_test(config, workdir: str, test_file: str, out_files: dict[str, str],
                   network_only: bool = False, ways: tuple[str, ...] = WAYS) -> None:
  """Decomposes every test tower from each trajectory of `ways` into each file
  of `out_files` ("refine": refined; "sample": the selection's winner alone);
  `network_only`: the network's own densities (its arg-max) on the fitted boxes, no
  sampling (a model that reads no trajectory), into out_files["sample"].

  With both files asked for, one refining pass writes both where it can: the winner before
  refinement is the candidate of least selection objective, on the same boxes (no drawn
  faces), over every step (no selection horizon) and at its slots (no mass matching)."""
  trained = checkpoints.load(workdir)
  e, size = config.eval, int(config.data.image_size)
  # the preset's settings with the depth fit (the test towers carry depth images) and no
  # screen (as measured: the screen is unmeasured on tracking)
  settings = DecomposeConfig.from_eval(e).replace(**{
      "fit.enabled": True, "fit.depth": True, "fit.image": False,
      "select.screen_steps": 0,
      **({"select.samples": 1, "select.rounds": 1, "select.inertia": False,
          "select.continuation": 0, "refine.starts": 1}
         if network_only else {})})
  one_pass = (settings.select.horizon == 0 and settings.fit.face_spread == 0
              and not settings.select.mass_match)
  passes = ([("refine", "sample")] if one_pass and "refine" in out_files else
            [(v,) for v in out_files])
  for variants in passes:
    refine = variants[0] == "refine"
    _decompose_pass(trained, settings.replace(**{"refine.enabled": refine}), size,
                    int(e.batch_size), test_file,
                    {v: out_files[v] for v in variants if v in out_files}, network_only,
                    ways)


def _decompose_pass(trained, settings: DecomposeConfig, size: int, batch: int,
                    test_file: str, out_files: dict[str, str], network_only: bool,
                    ways: tuple[str, ...]) -> None:
  fn = make_decompose_fn(trained, settings, camera=camera.camera_dict(size, size),
                         pushes=generation.pushes_of(trained[1].data))
  d = dict(np.load(test_file))
  n, k = d["valid"].shape
  tau = settings.select.tau(settings.fit.enabled)
  out = {v: {} for v in out_files}
  for way in ways:
    traj = d[f"{way}_trajectory"]
    ok = np.flatnonzero(np.isfinite(traj).all((1, 2)))
    fields = {v: {f: np.full((n, k) + d[f].shape[2:], np.nan, np.float32)
                  for f in primitives.FIELDS if f != "valid"} for v in out_files}
    valid = np.zeros((n, k), bool)
    score = {v: np.full(n, np.nan, np.float32) for v in out_files}
    for start in tqdm(range(0, len(ok), batch), desc=f"decompose ({way})"):
      chunk = ok[start:start + batch]
      padded = np.concatenate([chunk, np.full(batch - len(chunk), chunk[-1])])  # one compile
      obs = {"voxels": d["voxels"][padded], "image": d["image"][padded],
             "depth": d["depth"][padded], "trajectories": traj[padded][:, None]}
      res = jax.tree.map(lambda a: np.asarray(a)[:len(chunk)],
                         fn(obs, jax.random.key(int(chunk[0]))))
      valid[chunk] = res.primitives.valid
      for v in out_files:
        for f in fields[v]:
          fields[v][f][chunk] = getattr(res.primitives, f)
        score[v][chunk] = res.score
      if network_only:  # the network's arg-max, not the one sample's draw
        fields["sample"]["density"][chunk] = slot_to_density(np.argmax(res.density_logits, -1))
      elif "sample" in out_files and settings.refine.enabled:  # the winner before refinement
        cost = res.scores - tau * np.asarray(jax.vmap(sampling.log_prior)(
            res.density_logits, res.candidates, res.primitives.valid))
        best = np.argmin(cost, -1)
        slots = np.take_along_axis(res.candidates, best[:, None, None], 1)[:, 0]
        fields["sample"]["density"][chunk] = slot_to_density(slots)
        score["sample"][chunk] = np.take_along_axis(res.scores, best[:, None], 1)[:, 0]
    for v in out_files:
      out[v].update({f"{way}_{f}": x for f, x in fields[v].items()})
      out[v].update({f"{way}_valid": valid, f"{way}_score": score[v]})
  for v, path in out_files.items():
    np.savez_compressed(path, **out[v])
