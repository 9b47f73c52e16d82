"""`python -m ppdjax.decompose --mesh FILE --materials head=metal,handle=wood`: a user's mesh
decomposed into physical primitives.

Reads the mesh (`ppdjax.load_object`: parts are the file's groups or connected
components), observes it as the model's data were: a tools' model as the tools dataset
does (`tool_scene.observe`: exact voxels, a textured image, MuJoCo C trajectories of the
parts under the tools' four pushes); a towers' model (the blocks', the video's) upright as
the towers are (`mesh_towers.observe_tower`: the file's z up, its parts' boxes voxelized
and rendered from the towers' camera, simulated under the model's own pushes or read from
`--trajectory`); runs
`make_decompose_fn` with a trained model and its own settings
(`--config.eval.<key>=<value>` overrides one), and writes OUT/decomposition.png (the input
image, the recovered boxes coloured by density, the truth's boxes from the mesh) and
OUT/decomposition.json (the boxes in the normalised frame, the transform from the file's
coordinates, the parts and their densities).
"""

from __future__ import annotations

import json
import os

from absl import app, flags, logging

from ppdjax.configs import cli

_MESH = flags.DEFINE_string("mesh", None, "OBJ/STL/PLY/GLB file.", required=True)
_MATERIALS = flags.DEFINE_string("materials", "", "Materials per part: name=material,... "
                                 "(names: the file's groups, or part0, part1, ...), or one "
                                 "material for every part.")
_DENSITIES = flags.DEFINE_string("densities", "", "Densities per part in kg/m^3 "
                                 "(name=value,... or one value); override --materials'.")
_PROTOCOL = flags.DEFINE_enum(
    "protocol", "realistic", ["realistic", "paper"], "Which shipped tools model (without "
    "--model): 'realistic' (assets/tools_model: the mesh's parts are the body) or 'paper' "
    "(assets/tools_paper_model: the paper's protocol, the mesh's boxes are the body, as "
    "Table 3). The observation follows the model's own dataset either way.")
_MODEL = flags.DEFINE_string("model", "", "Trained model folder (default: the --protocol's "
                             "shipped tools model; the block-tower model if that is missing).")
_OUT = flags.DEFINE_string("out", "out/decompose", "Output directory.")
_ENGINE = flags.DEFINE_enum("engine", "", ["", "mjx", "box_plane"], "Engine that simulates "
                            "the boxes (default: the model's training engine).")
_SEED = flags.DEFINE_integer("seed", 0, "Sampling and texture seed.")
_TRAJECTORY = flags.DEFINE_string(
    "trajectory", "", "A tracked trajectory (python -m ppdjax.track's .npz) to read instead "
    "of simulating the mesh's motion: the object struck once as the video model was trained "
    "(default model then assets/video_model; the stickers' object frame must be the "
    "mesh's normalised frame).")
_CONFIG = cli.define_model_overrides(("eval",))


def _parse(text: str, number: bool):
  """"a=x,b=y" -> {"a": x, "b": y}; "x" -> x; "" -> None."""
  if not text:
    return None
  if "=" not in text:
    return float(text) if number else text
  out = {}
  for item in text.split(","):
    name, sep, value = item.partition("=")
    if not sep or not name.strip():
      raise ValueError(f"expected name=value pairs separated by commas, got {item!r}")
    out[name.strip()] = float(value) if number else value.strip()
  return out


SHIPPED = {"realistic": "assets/tools_model", "paper": "assets/tools_paper_model"}


def default_model(tracked: bool = False, protocol: str = "realistic") -> str:
  """The shipped model for a tracked trajectory, or for tools of `protocol`."""
  if tracked:
    return "assets/video_model"
  if protocol not in SHIPPED:
    raise ValueError(f"protocol must be one of {tuple(SHIPPED)}, got {protocol!r}")
  if os.path.isdir(SHIPPED[protocol]):
    return SHIPPED[protocol]
  logging.warning("%s is not shipped: decomposing with the block-tower model",
                  SHIPPED[protocol])
  return "assets/blocks_model"


def check_files(mesh: str, model: str, trajectory: str = "") -> None:
  """Refuses missing or unreadable inputs before anything slow: FileNotFoundError naming a
  missing mesh file or model folder; the model's config.json and the trajectory .npz are
  read now (CheckpointError, files.VideoFileError naming the file), not after the mesh's
  motion has been simulated."""
  from ppdjax.training.checkpoints import read_config  # pylint: disable=import-outside-toplevel
  from ppdjax.video.files import read_trajectory  # pylint: disable=import-outside-toplevel
  if not os.path.isfile(mesh):
    raise FileNotFoundError(f"{mesh}: no such mesh file (--mesh)")
  read_config(model)
  if trajectory:
    read_trajectory(trajectory)


def run(mesh: str, materials, densities, model: str, out: str, overrides: dict | None = None,
        engine: str = "", seed: int = 0, trajectory: str = "") -> dict:
  """Decomposes a mesh file; writes the picture and JSON into `out`; returns the JSON.

  Args:
    mesh: an OBJ, STL, PLY or GLB file (`ppdjax.load_object`).
    materials, densities: per part (a dict by part name) or one for all; see the flags.
    model: a trained model folder (`ppdjax.load`).
    out: the folder to write decomposition.png and decomposition.json into.
    overrides: keys of the model's `eval` section (`schema.EvalConfig`) to change.
    engine: "", "mjx" or "box_plane" ("": the model's training engine).
    seed: sampling and texture seed.
    trajectory: a `ppdjax.track` .npz whose tracked motion is the observation's ("":
      simulate the mesh's).

  Files are checked first (`check_files`).
  """
  check_files(mesh, model, trajectory)
  import jax
  import numpy as np

  from ppdjax import load, load_object, make_decompose_fn
  from ppdjax.report import plots
  from ppdjax.dataset import tool_generation, tool_paper, tool_scene
  from ppdjax.dataset.mesh_boxes import boxes_of_parts
  from ppdjax.infer.config import DecomposeConfig
  from ppdjax.infer.decompose import model_camera

  trained = load(model)
  _, config = trained
  # a towers' model (the blocks', the video's) reads a tower as the towers are observed:
  # upright, from the towers' camera (`mesh_towers`); a tools' model, as the tools are
  towers = config.data.get("kind", "towers") in ("towers", "pendulum")
  tool, transform = load_object(mesh, part_materials=materials, part_densities=densities,
                                upright=towers)
  print(f"{mesh}: {len(tool.parts)} parts "
        + ", ".join(f"{n} ({m}, {d:.0f} kg/m^3)" for n, m, d in
                    zip(tool.names, tool.materials, tool.densities)))
  if towers:
    from ppdjax.dataset.generation import pushes_of
    from ppdjax.dataset.mesh_towers import observe_tower
    from ppdjax.sim import scene
    from ppdjax.sim.simulate import simulate
    protocol, pushes = "towers", pushes_of(config.data)
    print(f"model {model}: towers ({config.data.kind}), observed upright as its data were")
    obs, truth = observe_tower(tool.parts, tool.materials, tool.densities, seed, config.data)
    rest = float(np.asarray(scene.rest_position(truth))[2])
    if not trajectory:  # the model's own pushes; MuJoCo C where JAX has no accelerator
      backend = config.data.backend if jax.default_backend() != "cpu" else "mujoco"
      obs["trajectories"] = np.asarray(simulate(truth, pushes, steps=int(config.data.steps),
                                                backend=backend), np.float32)
  else:
    # the pushes the model's data had for a tool of this volume (`tool_generation.tool_pushes`)
    pushes = tool_generation.tool_pushes(config.data, list(tool.parts))
    print(f"pushes of {float(pushes.magnitudes[0]):.4g} N "
          f"({tool_generation.push_mode(config.data)})")
    protocol = tool_generation.protocol(config.data)
    print(f"model {model}: " + (
        "tools under the paper's protocol (the mesh's boxes are the body, each of the "
        "material of the part it covers most)" if protocol == "paper" else
        "realistic tools (the mesh's parts are the body)"))
    rest = tool_scene.rest_height(list(tool.parts))
    if protocol == "paper":
      # the boxes on the model's engine where JAX has an accelerator, else MuJoCo C
      backend = config.data.backend if jax.default_backend() != "cpu" else "mujoco"
      obs, truth = tool_paper.observe(
          list(tool.parts), tool.materials, tool.densities, seed,
          image_size=int(config.data.image_size), steps=int(config.data.steps),
          pushes=pushes, backend=backend)
    else:
      obs = tool_scene.observe(list(tool.parts), tool.materials, tool.densities,
                               [seed] * len(tool.parts),
                               image_size=int(config.data.image_size),
                               steps=int(config.data.steps), pushes=pushes,
                               trajectories=not trajectory)
      truth, _ = boxes_of_parts(list(tool.parts), tool.densities)
  if trajectory:
    from ppdjax.video.files import tracked_observation
    obs["trajectories"] = tracked_observation(trajectory, config, rest)
  # simulated here under the pushes the model's data had; a tracked one under its own
  settings = DecomposeConfig.from_eval({**config.eval, **(overrides or {})})
  if settings.fit.depth and "depth" not in obs:
    print("the model's settings fit the boxes to a depth image, which this observation "
          "lacks: fitting them to the voxels (and the image, where the settings say) only")
    settings = settings.replace(**{"fit.depth": False})
  decompose = make_decompose_fn(trained, settings, pushes=None if trajectory else pushes,
                                engine=engine or None,
                                camera=model_camera(model) if settings.fit.with_ else None)
  samples = settings.select.samples
  print(f"decomposing with {model} ({samples} density candidates; the first call compiles)")
  result = jax.tree.map(np.asarray, decompose(obs, jax.random.key(seed)))
  os.makedirs(out, exist_ok=True)
  plots.plot_decomposition(obs["image"], result.primitives,
                           os.path.join(out, "decomposition.png"), true=truth,
                           title=f"{os.path.basename(mesh)}: trajectory distance "
                                 f"{float(result.score) * 1e3:.1f} mm")

  def boxes(p):
    return [{"half_size": p.half_size[k].tolist(), "pos": p.pos[k].tolist(),
             "quat": p.quat[k].tolist(), "density": float(p.density[k])}
            for k in np.flatnonzero(np.asarray(p.valid))]
  record = {"mesh": os.path.abspath(mesh), "model": model, "protocol": protocol,
            "transform_from_file": np.asarray(transform).tolist(),
            "parts": [{"name": n, "material": m, "density": float(d)} for n, m, d in
                      zip(tool.names, tool.materials, tool.densities)],
            "boxes": boxes(result.primitives), "boxes_from_mesh": boxes(truth),
            "trajectory_distance_m": float(result.score), "settings": settings.to_dict(),
            "trajectory": os.path.abspath(trajectory) if trajectory else "simulated"}
  with open(os.path.join(out, "decomposition.json"), "w") as f:
    json.dump(record, f, indent=1)
  print(f"wrote {out}/decomposition.png and {out}/decomposition.json")
  return record


def main(argv):
  del argv
  logging.set_verbosity(logging.WARNING)
  if _MODEL.value and _PROTOCOL.present:
    logging.warning("--protocol picks a shipped model only: --model=%s is used, and its "
                    "own data section says how the mesh is observed", _MODEL.value)
  import jax
  jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/ppdjax/jax_cache"))
  run(_MESH.value, _parse(_MATERIALS.value, number=False), _parse(_DENSITIES.value, number=True),
      _MODEL.value or default_model(bool(_TRAJECTORY.value), _PROTOCOL.value), _OUT.value,
      cli.model_overrides(("eval",))["eval"], _ENGINE.value, _SEED.value, _TRAJECTORY.value)


if __name__ == "__main__":
  app.run(main)
