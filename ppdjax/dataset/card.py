"""Dataset card: counts, density histogram, push statistics and a contact sheet."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ppdjax.conventions import TIMESTEP, density_to_slot  # noqa: E402
from ppdjax.dataset import materials, storage  # noqa: E402


def look_note(data: dict) -> str:
  """The card's sentences on look-alike blocks (`data.look`, `data.hollow`), empty for
  blocks that show their own material and are of it throughout."""
  look = {"material": "",
          "painted": " Look: one paint on every block (the texture tells no material).",
          "alike_metals": " Look: steel shows aluminium's finish (two materials, one look)."
          }[data.get("look", "material")]
  p = data.get("hollow", 0.0)
  return look + (f" Hollow: each block a shell around a core with probability {p:g} "
                 "(`dataset.hollow`; densities are the blocks' means)." if p else "")


def write_card(path: str, sheet_samples: int = 8) -> None:
  """Writes card.md, density_histogram.png and contact_sheet.png into dataset `path`."""
  ds = storage.open_dataset(path)
  load = lambda f: np.concatenate([np.load(os.path.join(path, s["name"], f"{f}.npy"),
                                           mmap_mode="r") for s in ds.manifest["shards"]])
  valid, mats, density = load("valid"), load("materials"), load("density")
  traj = load("trajectories")
  blocks = valid.sum(1)
  slots = density_to_slot(density[valid])

  fig, ax = plt.subplots(figsize=(7, 3))
  ax.hist(slots + 1, bins=np.arange(0.5, 101.5, 1), color="tab:blue")
  ax.set(xlabel="density (x100 kg/m³)", ylabel="blocks", title="density histogram")
  fig.tight_layout()
  fig.savefig(os.path.join(path, "density_histogram.png"), dpi=100)
  plt.close(fig)

  # displacement statistics per push (object-frame origin)
  start = traj[:, :, :1, :3]
  final = np.linalg.norm(traj[:, :, -1, :3] - start[:, :, 0], axis=-1)
  first = np.linalg.norm(traj[:, :, 1, :3] - traj[:, :, 0, :3], axis=-1) / TIMESTEP

  idx = np.linspace(0, len(ds) - 1, min(sheet_samples, len(ds))).astype(int)
  fig, axes = plt.subplots(len(idx), 3, figsize=(7.5, 2.5 * len(idx)))
  for row, i in enumerate(np.atleast_1d(idx)):
    s = ds[int(i)]
    names = [materials.ALL_MATERIAL_NAMES[m] for m in s["materials"] if m >= 0]
    axes[row, 0].imshow(s["image"])
    axes[row, 0].set_title(f"#{i} tower {s['tower_id']}: " + ", ".join(names), fontsize=7)
    axes[row, 1].imshow(s["voxels"].max(1).T, origin="lower", cmap="Greys", vmin=0, vmax=1)
    axes[row, 1].set_title("voxels, front (x-z)", fontsize=7)
    axes[row, 2].imshow(s["voxels"].max(2).T, origin="lower", cmap="Greys", vmin=0, vmax=1)
    axes[row, 2].set_title("voxels, top (x-y)", fontsize=7)
    for a in axes[row]:
      a.set_xticks([])
      a.set_yticks([])
  fig.tight_layout()
  fig.savefig(os.path.join(path, "contact_sheet.png"), dpi=80)
  plt.close(fig)

  m = ds.manifest
  lines = [f"# Dataset card: {m['config'].get('name', '?')} preset", "",
           (f"{m['tools']} tools x {m['config']['data'].get('configs_per_tool', 1)} density "
            f"configurations = {m['samples']} samples; splits by tool: " if "tools" in m else
            f"{m['towers']} towers x {m['config']['data']['configs_per_tower']} configurations "
            f"= {m['samples']} samples; splits by tower: ") +
           ", ".join(f"{k} {v}" for k, v in m["splits"].items()) +
           f". Engine: {m['engine']['backend']} ({m['engine']['precision']}), seed "
           f"{m['seed']}." + look_note(m['config']['data']), "",
           "| boxes | samples |", "|---|---|"]
  lines += [f"| {b} | {(blocks == b).sum()} |" for b in range(1, valid.shape[1] + 1)
            if (blocks == b).any()]
  lines += ["", "| material | blocks | density range seen (x100 kg/m³) |", "|---|---|---|"]
  real_set = bool((mats[valid] >= len(materials.MATERIAL_NAMES)).any())
  for k, name in enumerate(materials.ALL_MATERIAL_NAMES):
    sel = mats[valid] == k
    if not sel.any() and (name in materials.REAL_MATERIALS) != real_set:
      continue  # the other material set's rows
    rng = f"{slots[sel].min() + 1}-{slots[sel].max() + 1}" if sel.any() else "-"
    lines.append(f"| {name} | {int(sel.sum())} | {rng} |")
  lines += ["", "| push | speed after push, median / p90 (m/s) | displacement after "
            f"{traj.shape[2]} steps, median / p90 (m) |", "|---|---|---|"]
  for p in range(traj.shape[1]):
    lines.append(f"| {p} | {np.median(first[:, p]):.2f} / {np.percentile(first[:, p], 90):.2f}"
                 f" | {np.median(final[:, p]):.2f} / {np.percentile(final[:, p], 90):.2f} |")
  lines += ["", "![density histogram](density_histogram.png)", "",
            "![contact sheet](contact_sheet.png)", ""]
  with open(os.path.join(path, "card.md"), "w") as f:
    f.write("\n".join(lines))
