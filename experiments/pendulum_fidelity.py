"""How well the strike's impulse model (`pendulum_strike`) stands for a simulated pendulum.

  python experiments/pendulum_fidelity.py            # 48 towers, about a minute on a CPU

For towers of the real blocks (2-4 blocks, seed --seed), MuJoCo C simulates the whole
event: a copper ball (radius BALL_RADIUS) on a massless string of PENDULUM_LENGTH,
released at RELEASE_ANGLE, swinging through its lowest point at the strike point. Its
tower trajectory from the first ball-tower contact on is compared with MuJoCo C under
the impulse model (`ppdjax.simulate(prims, pendulum_strike(restitution=e))`) for several
e: position gap after 0.1 s and after 256 steps, and the tower's speed after the strike.
MuJoCo's soft contact has no restitution parameter (its bounce follows from solref); the
study reads which e the full simulation behaves like. Writes OUT/pendulum_fidelity.{md,json}.
"""

from __future__ import annotations

import json
import os
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from absl import app, flags

import ppdjax
from ppdjax.conventions import STEPS, TIMESTEP
from ppdjax.dataset import towers
from ppdjax.sim import pushes as pushes_module
from ppdjax.sim import scene

flags.DEFINE_integer("towers", 48, "How many towers.")
flags.DEFINE_integer("seed", 31, "Tower seed.")
flags.DEFINE_string("out", "experiments/results", "Where the report goes.")
flags.DEFINE_string("ball_solref", "", "The ball's contact solref (time constant, damping "
                    "ratio); empty: MuJoCo's default, 0.02 1.")
FLAGS = flags.FLAGS
RESTITUTIONS = (0.0, 0.25, 0.5)


def pendulum_xml(tower, strike_point_world: np.ndarray) -> str:
  """The scene of `scene.scene_xml` with the pendulum: its ball at the bottom of the swing
  touches the strike point from -y."""
  p = jax.tree.map(np.asarray, tower)
  boxes = [dict(size=p.half_size[k], pos=p.pos[k], quat=p.quat[k], density=float(p.density[k]))
           for k in np.flatnonzero(p.valid)]
  r, length = pushes_module.BALL_RADIUS, pushes_module.PENDULUM_LENGTH
  pivot = [float(v) for v in strike_point_world + np.array([0.0, -r, length])]
  pendulum = (f'    <body name="pendulum" pos="{pivot[0]!r} {pivot[1]!r} {pivot[2]!r}">\n'
              f'      <joint name="swing" type="hinge" axis="1 0 0"/>\n'
              f'      <geom name="ball" type="sphere" size="{r!r}" pos="0 0 {-length!r}" '
              f'density="{pushes_module.COPPER_DENSITY!r}"'
              + (f' solref="{FLAGS.ball_solref}"' if FLAGS.ball_solref else "") + '/>\n'
              '    </body>\n')
  return scene.scene_xml(boxes).replace("  </worldbody>", pendulum + "  </worldbody>")


def full_event(tower) -> tuple[np.ndarray, float]:
  """(STEPS, 7) tower poses from the first ball contact on, and the ball's speed then."""
  one = jax.tree.map(jnp.asarray, tower)
  rest = np.asarray(scene.rest_position(one))
  point = np.asarray(pushes_module.push_points(one, pushes_module.pendulum_strike()))[0] + rest
  model = mujoco.MjModel.from_xml_string(pendulum_xml(tower, point))
  data = mujoco.MjData(model)
  data.qpos[:3], data.qpos[3:7] = rest, [1.0, 0.0, 0.0, 0.0]
  data.qpos[7] = -np.radians(pushes_module.RELEASE_ANGLE)
  ball = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "ball")
  poses, speed = [], None
  for _ in range(int(3.0 / TIMESTEP)):
    before = abs(float(data.qvel[6])) * pushes_module.PENDULUM_LENGTH  # ball speed
    mujoco.mj_step(model, data)
    touching = any(ball in (c.geom1, c.geom2) for c in data.contact[:data.ncon])
    if speed is None and touching:
      speed = before
    if speed is not None:
      poses.append(data.qpos[:7].copy())
      if len(poses) == STEPS:
        return np.asarray(poses), speed
  raise RuntimeError("the ball never reached the tower")


def main(argv):
  del argv
  rng = np.random.default_rng(FLAGS.seed)
  prims = ppdjax.primitives.stack([towers.sample_tower(rng, 2 + i % 3, material_set="real")[0]
                                   for i in range(FLAGS.towers)])
  full, speeds = zip(*[full_event(jax.tree.map(lambda a, i=i: np.asarray(a)[i], prims))
                       for i in range(FLAGS.towers)])
  full = np.asarray(full)
  gap = lambda a, b, t: 1e3 * np.linalg.norm(a[:, t, :3] - b[:, t, :3], axis=-1)  # noqa: E731
  early = int(round(0.1 / TIMESTEP)) - 1
  disp = np.linalg.norm(full[:, -1, :3] - full[:, 0, :3], axis=-1)
  rows = {}
  for e in RESTITUTIONS:
    model = np.asarray(ppdjax.simulate(prims, pushes_module.pendulum_strike(restitution=e),
                                       backend="mujoco"))[:, 0]
    # the tower's peak speed along the strike within 0.05 s: the full event's contact is
    # soft and lasts several steps, the impulse model's one
    peak = lambda t: (np.diff(t[:, :16, 1], axis=1) / TIMESTEP).max(1)  # noqa: E731
    v_full, v_model = peak(full), peak(model)
    rows[f"{e:g}"] = {
        "gap_0.1s_mm_median": float(np.median(gap(full, model, early))),
        "gap_0.1s_mm_p90": float(np.percentile(gap(full, model, early), 90)),
        "gap_end_mm_median": float(np.median(gap(full, model, -1))),
        "gap_end_mm_p90": float(np.percentile(gap(full, model, -1), 90)),
        "speed_ratio_median": float(np.median(v_model / v_full)),
        "speed_ratio_p10_p90": [float(np.percentile(v_model / v_full, q)) for q in (10, 90)]}
  command = "python experiments/pendulum_fidelity.py " + " ".join(sys.argv[1:])
  result = {"command": command, "towers": FLAGS.towers, "seed": FLAGS.seed,
            "ball_speed_at_contact_m_s": float(np.median(speeds)),
            "full_displacement_m_median": float(np.median(disp)), "restitution": rows}
  os.makedirs(FLAGS.out, exist_ok=True)
  with open(os.path.join(FLAGS.out, "pendulum_fidelity.json"), "w") as f:
    json.dump(result, f, indent=1)
  lines = ["# The strike's impulse model against a simulated pendulum", "", f"`{command}`", "",
           f"{FLAGS.towers} towers of the real blocks (2-4 blocks, seed {FLAGS.seed}); MuJoCo C "
           "simulates the ball on its string (reaching the tower at "
           f"{result['ball_speed_at_contact_m_s']:.2f} m/s) and, separately, the impulse model "
           "of `pendulum_strike(restitution=e)`. Gaps: tower position, full pendulum vs "
           "impulse model, from the first ball contact on (median tower displacement over "
           f"256 steps: {result['full_displacement_m_median']:.2f} m). Speed ratio: the "
           "tower's peak speed along the strike within 0.05 s of the first contact, impulse "
           "model / full pendulum.", "",
           "| e | gap after 0.1 s, median / p90 (mm) | gap after 256 steps, median / p90 (mm) | "
           "speed ratio, median [p10, p90] |", "|--:|--:|--:|--:|"]
  for e, r in rows.items():
    lo, hi = r["speed_ratio_p10_p90"]
    lines.append(f"| {e} | {r['gap_0.1s_mm_median']:.1f} / {r['gap_0.1s_mm_p90']:.1f} | "
                 f"{r['gap_end_mm_median']:.0f} / {r['gap_end_mm_p90']:.0f} | "
                 f"{r['speed_ratio_median']:.2f} [{lo:.2f}, {hi:.2f}] |")
  with open(os.path.join(FLAGS.out, "pendulum_fidelity.md"), "w") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


if __name__ == "__main__":
  app.run(main)
