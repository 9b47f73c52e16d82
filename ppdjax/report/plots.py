"""Figures: a tower and its push trajectories; learning curves; confusion; decompositions."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ppdjax.conventions import TIMESTEP  # noqa: E402
from ppdjax.primitives import corners  # noqa: E402
from ppdjax.sim.pushes import push_points  # noqa: E402
from ppdjax.sim.scene import rest_position  # noqa: E402

_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def plot_trajectories(prims, pushes, traj, ref=None, path="trajectories.png",
                      labels=("mjx", "mujoco")):
  """Side view of the tower with its pushes, height over time, and top-down paths.

  Args:
    prims: one object (K slots).
    pushes: Pushes.
    traj: (P, T, 7) trajectories to show (solid).
    ref: optional (P, T, 7) reference trajectories (dashed).
    path: PNG file.
    labels: names of the two engines.
  """
  import jax
  import jax.numpy as jnp

  p = jax.tree.map(jnp.asarray, prims)
  rest = np.asarray(rest_position(p))
  box_corners = np.asarray(corners(p)) + rest
  valid = np.asarray(p.valid)
  density = np.asarray(p.density)
  points = np.asarray(push_points(p, pushes)) + rest
  sources = np.asarray(pushes.sources) + rest
  t = np.arange(1, traj.shape[1] + 1) * TIMESTEP

  fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
  ax = axes[0]
  cmap = plt.get_cmap("viridis")
  for k in np.flatnonzero(valid):
    c = box_corners[k][:, [0, 2]]  # side view: x-z
    lo, hi = c.min(0), c.max(0)
    ax.add_patch(plt.Rectangle(lo, *(hi - lo), alpha=0.6,
                               color=cmap(min(density[k] / 10000.0, 1.0)), ec="k"))
    ax.text(*(lo + hi) / 2, f"{density[k]:.0f}", ha="center", va="center", fontsize=8)
  for i in range(len(points)):
    ax.annotate("", xy=points[i, [0, 2]], xytext=sources[i, [0, 2]],
                arrowprops=dict(arrowstyle="->", color=_COLORS[i % 6], lw=1.5))
  ax.axhline(0, color="gray", lw=1)
  ax.set(xlim=(-1.3, 1.3), ylim=(-0.6, 1.7), aspect="equal", xlabel="x (m)", ylabel="z (m)",
         title="tower at rest (x-z), density kg/m³, pushes")

  for i in range(traj.shape[0]):
    col = _COLORS[i % 6]
    axes[1].plot(t, traj[i, :, 2], color=col, label=f"push {i}")
    axes[2].plot(traj[i, :, 0], traj[i, :, 1], color=col, label=f"push {i}")
    if ref is not None:
      axes[1].plot(t, ref[i, :, 2], color=col, ls="--", lw=1)
      axes[2].plot(ref[i, :, 0], ref[i, :, 1], color=col, ls="--", lw=1)
  suffix = f" ({labels[0]} solid, {labels[1]} dashed)" if ref is not None else ""
  axes[1].set(xlabel="time (s)", ylabel="object-frame origin z (m)", title="height" + suffix)
  axes[2].set(xlabel="x (m)", ylabel="y (m)", aspect="equal", title="top-down path" + suffix)
  axes[2].plot([0], [0], "k+")
  axes[1].legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot_learning_curve(metrics_path: str, path: str = "learning_curve.png") -> str:
  """Training and validation losses and validation metrics over steps, from metrics.jsonl."""
  import json
  with open(metrics_path) as f:
    rows = [json.loads(line) for line in f if line.strip()]
  train = [r for r in rows if r.get("split", "train") == "train"]
  val = [r for r in rows if r.get("split") == "val"]
  fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
  for key, style in (("loss", "-"), ("geometry_loss", "--"), ("stream_geometry_loss", "-."),
                     ("end_loss", (0, (1, 3))), ("density_loss", ":")):
    rows_k = [r for r in train if key in r]  # the stream phase has no density loss
    if rows_k:
      axes[0].plot([r["step"] for r in rows_k], [r[key] for r in rows_k], linestyle=style,
                   label=f"train {key}")
  axes[0].plot([r["step"] for r in val], [r["loss"] for r in val], "o-", label="val loss")
  axes[0].set_yscale("log")
  axes[0].set_title("losses (grey lines: phase starts)")
  phases = sorted({r.get("phase", 1) for r in train})
  starts = [min(r["step"] for r in train if r.get("phase", 1) == p) for p in phases[1:]]
  for ax in axes:
    for s in starts:
      ax.axvline(s, color="grey", lw=0.8)
    ax.set_xlabel("step")
  for key in ("density_top1", "density_top5", "density_top10", "shape_f1"):
    axes[1].plot([r["step"] for r in val], [r[key] for r in val], "o-", label=key)
  axes[1].set_title("validation (%)")
  axes[2].plot([r["step"] for r in val], [r["density_rmse"] for r in val], "o-", color="k")
  axes[2].set_title("validation density RMSE (slots)")
  for ax in axes[:2]:
    ax.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return path


def plot_variant_curves(metrics_paths: dict, path: str = "learning_curves.png") -> str:
  """Learning curves of several runs side by side: {name: metrics.jsonl path}."""
  import json
  fig, axes = plt.subplots(1, 4, figsize=(18, 3.8))
  for i, (name, file) in enumerate(metrics_paths.items()):
    if not os.path.exists(file):
      continue
    with open(file) as f:
      rows = [json.loads(line) for line in f if line.strip()]
    train = [r for r in rows if r.get("split", "train") == "train"]
    val = [r for r in rows if r.get("split") == "val"]
    c = f"C{i}"
    axes[0].plot([r["step"] for r in train], [r["geometry_loss"] for r in train], color=c,
                 label=name)
    joint = [r for r in train if "density_loss" in r]
    axes[1].plot([r["step"] for r in joint], [r["density_loss"] for r in joint], color=c,
                 alpha=0.6, label=f"{name} train")
    axes[1].plot([r["step"] for r in val], [r["density_loss"] for r in val], "o--", color=c,
                 label=f"{name} val")
    axes[2].plot([r["step"] for r in val], [r["shape_f1"] for r in val], "o-", color=c,
                 label=name)
    axes[3].plot([r["step"] for r in val], [r["density_top1"] for r in val], "o-", color=c,
                 label=name)
  axes[0].set(title="geometry loss (train)", yscale="log", xlabel="step")
  axes[1].set(title="density loss", yscale="log", xlabel="step")
  axes[2].set(title="validation shape F1 (%)", xlabel="step")
  axes[3].set(title="validation density top-1 (%)", xlabel="step")
  for ax in axes:
    ax.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return path


def plot_confusion(confusion: dict, path: str = "confusion.png") -> str:
  """Row-normalised density confusion matrices (true slot × predicted slot), one per row."""
  names = list(confusion)
  fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 4.0), squeeze=False)
  for ax, name in zip(axes[0], names):
    m = np.asarray(confusion[name], np.float64)
    m = m / np.maximum(m.sum(1, keepdims=True), 1.0)
    ax.imshow(m, origin="lower", cmap="magma", vmin=0, vmax=max(m.max(), 1e-6),
              extent=(0.5, 100.5, 0.5, 100.5))
    ax.set_title(name, fontsize=9)
    ax.set_xlabel("predicted density (×100 kg/m³)")
    ax.set_ylabel("true density (×100 kg/m³)")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return path


def plot_decomposition(image, prims, path: str = "decomposition.png", true=None,
                       title: str = "") -> str:
  """The input image beside the recovered boxes coloured by density (and the truth's)."""
  from matplotlib import cm, colors
  from mpl_toolkits.mplot3d.art3d import Poly3DCollection

  faces = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
  norm = colors.Normalize(100.0, 10000.0)
  cmap = matplotlib.colormaps["viridis"]
  shown = [("recovered", prims)] + ([("ground truth", true)] if true is not None else [])
  fig = plt.figure(figsize=(4.2 * (1 + len(shown)) + 0.8, 4.2))
  ax = fig.add_subplot(1, 1 + len(shown), 1)
  ax.imshow(np.asarray(image))
  ax.set_title("input image")
  ax.axis("off")
  for i, (name, p) in enumerate(shown):
    ax = fig.add_subplot(1, 1 + len(shown), i + 2, projection="3d")
    c = np.asarray(corners(p))
    for k in np.nonzero(np.asarray(p.valid))[0]:
      poly = [[c[k, j] for j in f] for f in faces]
      d = float(np.asarray(p.density)[k])
      ax.add_collection3d(Poly3DCollection(poly, facecolor=cmap(norm(d)), edgecolor="k",
                                           linewidth=0.5, alpha=0.9))
      ax.text(*c[k].mean(0), f"{d:.0f}", fontsize=7, ha="center")
    ax.set(xlim=(-0.6, 0.6), ylim=(-0.6, 0.6), zlim=(-0.6, 0.6), title=name)
    ax.set_box_aspect((1, 1, 1))
  fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=fig.axes, shrink=0.8,
               label="density (kg/m³)")
  if title:
    fig.suptitle(title, fontsize=9)
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return path
