"""The candidates every row of an evaluation scores, drawn and simulated per object:
`decompose`'s on the network's and the fitted boxes, the true densities (Oracle's
baseline), and Table 4's sampling baselines."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ppdjax.conventions import NUM_DENSITY_SLOTS, slot_to_density_jax
from ppdjax.eval import baselines
from ppdjax.infer import sampling
from ppdjax.report.tables import SELECTION_HORIZONS


def simultaneous_candidates() -> int:
  """Candidates simulated at once (objects × candidates; × 4 pushes in rollouts): 16,384
  on an accelerator (65,536 rollouts run at ~10× the rate of 2,048, benchmarks.md), 2,048
  on a CPU."""
  return 2048 if jax.default_backend() == "cpu" else 16384


def _table4_candidates(t, pool, kk, samples: int):
  """Table 4's sampling baselines for one object (`candidate_layout`'s "uniform" and
  "shapes"): `samples` uniform densities on its true boxes `t`, then `pool` (random tower
  shapes) with uniform densities; `kk` (4,) the object's derived keys."""
  uniform, _ = sampling.candidate_slots(jnp.zeros(t.valid.shape + (NUM_DENSITY_SLOTS,)),
                                        t.valid, samples, kk[1], include_mode=False)
  shape_slots = jax.random.randint(kk[2], (samples, t.density.shape[-1]), 0, NUM_DENSITY_SLOTS)
  return [sampling.with_slots(t, uniform),
          pool.replace(density=slot_to_density_jax(shape_slots))]


def simulate_candidates(pred, fitted, logits, fit_logits, true, base_slots, obs_traj, keys,
                        mags, pool=None, *, samples, with_baselines, chunk, pushes, settings, face_spreads=None,
              ppd_key_is_own=False):
  """Per object: (distance (C, H) over each of SELECTION_HORIZONS, MAE (C,)) of every
  candidate (`candidate_layout`; Table 4's too when `pool`, its random tower shapes, is
  given), the network's candidate slots on its boxes, and a tuple of them on each of
  `fitted` (a tuple of the fit groups' boxes, in layout order, scored by `fit_logits`, a
  tuple alike). `keys` (B,): each object's own (`decompose.object_keys`): the fit groups
  draw from it as `decompose` does (`sampling.select_densities`), so that the row of
  `decompose`'s settings holds its candidates; the network's boxes draw from it too where
  they are `decompose`'s (`ppd_key_is_own`: no fit), else from a key derived from it.
  `face_spreads`: per fit group, > 0 draws its candidates' faces too."""
  def one(args):
    p, fs, lg, flg, t, bs, traj, k, m = args
    kk = jax.random.split(k, 4)
    slots, _ = sampling.candidate_slots(lg, p.valid, samples, k if ppd_key_is_own else kk[0])
    cands = [sampling.with_slots(p, slots)]
    fit_slots = []
    spreads = face_spreads or (0.0,) * len(fs)
    for f, fl, spread in zip(fs, flg, spreads):  # one key for every fit group: rows with
      # the same scores differ by the boxes alone
      fit_slots.append(sampling.candidate_slots(fl, f.valid, samples, k)[0])
      cands.append(sampling.candidate_boxes(f, fit_slots[-1], jax.random.fold_in(k, 1),
                                            spread))
    if with_baselines:
      cands.append(sampling.with_slots(t, bs))
    if pool is not None:
      cands += _table4_candidates(t, pool, kk, samples)
    cands = jax.tree.map(lambda *x: jnp.concatenate(x), *cands)
    dist, mae = sampling.score_candidates(cands, traj, pushes.replace(magnitudes=m), settings,
                                          horizons=SELECTION_HORIZONS)
    return dist, mae, slots, tuple(fit_slots)

  return jax.lax.map(one, (pred, fitted, logits, fit_logits, true, base_slots, obs_traj, keys,
                           mags), batch_size=chunk)


def simulate_table4(true, pool, obs_traj, keys, mags, *, samples, chunk, pushes, settings):
  """Table 4's sampling baselines per object, (distance (C, H), MAE (C,)) of
  `_table4_candidates`: on the batches Table 4 covers when it covers only some."""
  def one(args):
    t, traj, k, m = args
    cands = jax.tree.map(lambda *x: jnp.concatenate(x),
                         *_table4_candidates(t, pool, jax.random.split(k, 4), samples))
    return sampling.score_candidates(cands, traj, pushes.replace(magnitudes=m), settings,
                                     horizons=SELECTION_HORIZONS)

  return jax.lax.map(one, (true, obs_traj, keys, mags), batch_size=chunk)


def shape_pool(key, samples: int, num_slots: int):
  """Table 4's "Sample Phys.+Shape" pool for one batch: `samples` random tower shapes
  (`baselines.random_shapes`) drawn from the batch's key."""
  return baselines.random_shapes(key, samples, num_slots)
