"""Episodes with a feature map crossed with the actions -> state features stored once per
observation (:mod:`r2pvi.data.storage.crossed`).

:func:`~r2pvi.data.episodes.from_episodes` takes this path when the feature map is an
:class:`~r2pvi.features.ActionCrossing` whose observation map gives dense rows: the dataset
holds ``psi`` of every observation (``T + 1`` rows per episode) and the actions as
indices instead of ``(1 + A) A m`` features per transition. The numbers it stands for are
those of the dense layout: the same rows, zero rows after an episode's end, the same
padding of next states (see :mod:`r2pvi.data.episodes`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import storage as _st
from .build import check_simplex_features
from .storage.crossed import CrossedField, CrossedNext

# Observations transformed per call of the observation map: bounds the map's temporaries.
_MAP_CHUNK = 1 << 14


def state_features(fmap, observations: np.ndarray, dtype) -> np.ndarray | None:
    """``psi`` of every observation ``(N, m)`` in ``dtype``, by chunk; None when the map gives
    sparse rows (they stay sparse rows: :mod:`r2pvi.data.build_sparse`)."""
    N = observations.shape[0]
    out = None
    for s in range(0, max(N, 1), _MAP_CHUNK):
        part = fmap.state_features(observations[s:s + _MAP_CHUNK])
        if sp.issparse(part):
            return None
        part = np.asarray(part)
        if part.ndim != 2 or part.shape[0] != min(N, s + _MAP_CHUNK) - s:
            raise ValueError(
                f"the observation map of the feature map returned shape {part.shape} for "
                f"{min(N, s + _MAP_CHUNK) - s} observations; expected (n, m)")
        if out is None:
            out = np.empty((N, part.shape[1]), dtype=dtype)
        if not np.isfinite(part).all():
            i = s + int(np.flatnonzero(~np.isfinite(part).all(axis=1))[0])
            raise ValueError(
                f"the feature map's observation map returned NaN or infinite features for "
                f"observation {i} (of all episodes' observations, in order): fix the map or "
                "the observations")
        out[s:s + part.shape[0]] = part
    return out


def crossed_episodes(cls, fmap, eps, lengths, h_idx, k_idx, cur, nxt, acts, rewards,
                     absorbing, offset, K, H, A, check_simplex, dtype):
    """The dataset of episodes ``eps`` (validated arrays) in the state-feature layout, or
    None when the observation map gives sparse rows. ``rewards`` are shifted already."""
    dtype = np.dtype(np.float64 if dtype is None else dtype)
    obs = np.concatenate([e[0][:n + 1] for e, n in zip(eps, lengths, strict=True)])
    psi_obs = state_features(fmap, obs, dtype)
    if psi_obs is None:
        return None
    m = psi_obs.shape[1]
    t_obs = np.concatenate([np.arange(n + 1) for n in lengths])
    k_obs = np.repeat(np.arange(K), lengths + 1)
    if check_simplex:
        # the rows fits use: every observation but a terminated episode's last (its
        # next-state value is known)
        last = np.cumsum(lengths + 1) - 1
        keep = np.ones(len(t_obs), dtype=bool)
        for k, e in enumerate(eps):
            if len(e[2]) <= H and len(e[2]) and e[3][-1]:
                keep[last[k]] = False
        check_simplex_features(psi_obs[keep], "feature_map(observations, actions)")
    psi = np.zeros((H + 1, K, m), dtype=dtype)
    psi[t_obs, k_obs] = psi_obs
    del psi_obs
    actions = np.full((H, K), -1, dtype=np.int64)
    actions[h_idx, k_idx] = acts
    rew = np.zeros((H, K))
    rew[h_idx, k_idx] = rewards
    known = np.full((H, K, A), np.nan)
    known[h_idx[absorbing], k_idx[absorbing]] = (H - h_idx[absorbing] - 1)[:, None] * offset
    # Padding: a step's empty rows repeat the next state of the first episode that reaches
    # it (their next observation's slot is free: the episode has ended before it).
    real = actions >= 0
    for h, src, pad in padded_steps(real):
        psi[h + 1, pad] = psi[h + 1, src]
        known[h, pad] = known[h, src]
    any_known = bool((~np.isnan(known[: H - 1])).any())
    used_next = psi[1:H]  # the next states of steps 0 .. H-2 (the last step's are not data)
    nonneg_next = bool((used_next >= 0).all())
    nonneg_phi = bool((psi[:H][real] >= 0).all())
    extras = episode_extras(cur, nxt, h_idx, k_idx, acts, K, H)
    for a in (psi, actions, rew, known):
        a.flags.writeable = False
    source = _st.StepSource(
        CrossedField(psi, actions, A), _st.ArrayField(rew),
        CrossedNext(psi, A, _st.ArrayField(known) if any_known else None, nonneg_next),
        extras, nonneg_phi, unit_rows=False,
        reward_range=(float(rew.min()), float(rew.max())),
        checked=("phi", "rewards", "next"), stationary=True, reward_offset=offset)
    return cls(_source=source)


def padded_steps(real: np.ndarray):
    """``(h, src, pad)`` for every step ``h`` with empty rows (``real (H, K)`` False) that some
    episode reaches: ``pad`` masks the empty rows, ``src`` is the first episode with a real
    transition there, whose next state the empty rows repeat (see :mod:`r2pvi.data.episodes`)."""
    for h in np.flatnonzero(~real.all(axis=1)):
        have = np.flatnonzero(real[h])
        if have.size:
            yield h, have[0], ~real[h]


def episode_extras(cur, nxt, h_idx, k_idx, acts, K, H) -> dict:
    """``states``, ``actions`` and ``next_states`` ``(K, H, ...)`` from the flattened real
    steps (zeros after an episode's end; a padded next state repeats the first episode's that
    reaches the step), read-only."""
    states = np.zeros((K, H) + cur.shape[1:], dtype=cur.dtype)
    next_states = np.zeros((K, H) + cur.shape[1:], dtype=cur.dtype)
    actions = np.zeros((K, H), dtype=np.int64)
    states[k_idx, h_idx] = cur
    next_states[k_idx, h_idx] = nxt
    actions[k_idx, h_idx] = acts
    real = np.zeros((H, K), dtype=bool)
    real[h_idx, k_idx] = True
    for h, src, pad in padded_steps(real):
        next_states[pad, h] = next_states[src, h]
    out = {}
    for name, value in (("states", states), ("actions", actions),
                        ("next_states", next_states)):
        value.flags.writeable = False
        out[name] = value
    return out
