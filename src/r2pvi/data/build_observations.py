"""The constructors of :class:`~r2pvi.OfflineDataset` from observations and a feature map:
features computed once and stored (:func:`from_transitions`), or a chunk at a time while
fitting (:func:`from_observations`). Bound to ``OfflineDataset`` as classmethods (see
:mod:`~r2pvi.data.build`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .._validation import as_array, as_index_array
from . import storage as _st
from .build import _check_feature_map, check_simplex_features

__all__ = ["from_observations", "from_transitions"]


def from_observations(
    cls, states, actions, rewards, next_states, feature_map, n_actions: int,
    next_values=None, *, check_simplex: bool = True,
):
    """Stored observations and a feature map evaluated chunk by chunk while fitting.

    The arguments of :meth:`from_transitions`, but no feature is stored: the taken-action
    features ``feature_map(states[:, h], actions[:, h])`` and every action's features at
    the next states are computed a chunk of trajectories at a time, each step, and never
    held for the whole dataset (a step's ``(K, d)`` taken-action features are). Arrays
    (memory maps included) are kept as step-major views when they are laid out so, else
    copied once. :meth:`save` stores the observations; :meth:`open` then needs the same
    ``feature_map``. The rewards are checked here; the features, computed while fitting,
    by the fit (a ``feature_map`` that returns NaN or an infinity is a ``ValueError``
    naming the step, trajectory and feature).

    Parameters
    ----------
    states, next_states : array_like (K, H, ...)
        Observations ``s_h`` and ``s_{h+1}`` (row ``h = H-1`` of ``next_states`` is never
        used).
    actions : array_like of int (K, H)
        Taken actions, indices in ``[0, n_actions)``.
    rewards : array_like (K, H)
    feature_map : callable
        ``feature_map(observations (n, ...), actions (n,)) -> (n, d)``.
    n_actions : int
    next_values : callable, optional
        ``next_values(next_states (n, ...)) -> (n, A)``, known action values (NaN: learn).
    check_simplex : bool, default True
        Warn when the features of the first chunk of trajectories leave the simplex.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> fmap = lambda x, a: np.stack([x[:, 0] * (a == 0), x[:, 0] * (a == 1),
    ...                               1 - x[:, 0]], axis=1)
    >>> rng = np.random.default_rng(0)
    >>> obs, nxt = rng.random((20, 3, 1)), rng.random((20, 3, 1))
    >>> ds = OfflineDataset.from_observations(obs, rng.integers(2, size=(20, 3)),
    ...                                       rng.random((20, 3)), nxt, fmap, 2)
    >>> ds.phi.shape, ds.next_phi.shape
    ((20, 3, 3), (20, 3, 2, 3))
    """
    _check_feature_map(feature_map, n_actions)
    if next_values is not None and not callable(next_values):
        raise TypeError("next_values must be callable: next_values(next_states) -> (n, A)")
    act = as_array(actions, "actions")
    if act.ndim != 2:
        raise ValueError(f"actions must have shape (K, H), got {act.shape}")
    if not np.issubdtype(act.dtype, np.integer):
        raise TypeError(f"actions must be integer action indices, got dtype {act.dtype}")
    K, H = act.shape
    if K == 0 or H == 0:
        raise ValueError(f"actions must have K >= 1 and H >= 1, got {act.shape}")
    obs, nobs = as_array(states, "states"), as_array(next_states, "next_states")
    if obs.shape[:2] != (K, H) or nobs.shape[:2] != (K, H):
        raise ValueError(
            f"states and next_states must start with (K, H) = {(K, H)} like actions, got "
            f"{obs.shape} and {nobs.shape}")
    r = _st.step_major(rewards, "rewards", 2, np.float64)
    if r.shape != (H, K):
        raise ValueError(f"rewards must have shape (K, H) = {(K, H)}, got {np.shape(rewards)}")
    if not all(np.isfinite(r[h]).all() for h in range(H)):
        raise ValueError("rewards contains NaN or infinite entries; clean the data first")
    sm = [_st.ArrayField(_st.layout_step_major(x)) for x in (obs, act, nobs)]
    for name, field in (("states", sm[0]), ("next_states", sm[2])):
        _check_finite_observations(field, name, H)
    for h in range(H):
        for _, _, rows in sm[1].chunks(h, _st.CHUNK):
            if rows.size and (rows.min() < 0 or rows.max() >= n_actions):
                raise ValueError(f"actions must lie in [0, {n_actions}); got values outside")
    probe = np.asarray(feature_map(sm[0].read(0, 0, 1), sm[1].read(0, 0, 1).astype(np.int64)))
    if probe.ndim != 2 or probe.shape[0] != 1 or probe.shape[1] < 1:
        raise ValueError(f"feature_map must return (n, d) for n observations, got "
                         f"{probe.shape} for one")
    d = probe.shape[1]
    phi = _st.MappedField(sm[0], sm[1], feature_map, d)
    nxt = _st.MapNext(sm[2], feature_map, int(n_actions), d, next_values)
    if check_simplex:
        first = phi.read(0, 0, _st.CHUNK)
        check_simplex_features(first, "phi")
        if H > 1:
            check_simplex_features(nxt.features(0, 0, _st.CHUNK), "next_phi")
    # the rewards are checked here; the features, computed while fitting, by the fit
    return cls(_source=_st.StepSource(phi, _st.ArrayField(r), nxt, {},
                                      reward_range=(float(r.min()), float(r.max())),
                                      checked=("rewards",)))



def from_transitions(
    cls,
    states,
    actions,
    rewards,
    next_states,
    feature_map: Callable[[np.ndarray, np.ndarray], np.ndarray],
    n_actions: int,
    next_values=None,
    *,
    check_simplex: bool = True,
):
    """Build a dataset from observed states and actions and a vectorized feature map.

    Parameters
    ----------
    states, next_states : array_like (K, H, ...)
        Observed states ``s_h`` and ``s_{h+1}`` (any trailing shape: integer indices,
        prices, vectors).
    actions : array_like of int (K, H)
        Taken actions, indices in ``[0, n_actions)``.
    rewards : array_like (K, H)
    feature_map : callable
        ``feature_map(states, actions) -> (n, d)`` for ``states`` of shape ``(n, ...)``
        and integer ``actions`` of shape ``(n,)``; it is called once for the taken
        actions and once per action for the next states.
    n_actions : int
        Number of actions A.
    next_values : array_like (K, H, A) or callable, optional
        Known next-state action values (NaN: learn), or ``next_values(next_states)``
        returning ``(n, A)`` for ``next_states`` of shape ``(n, ...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> onehot = lambda s, a: np.eye(4)[2 * s + a]       # 2 states x 2 actions
    >>> s = np.array([[0, 1]]); a = np.array([[1, 0]])
    >>> ds = OfflineDataset.from_transitions(s, a, [[0.0, 1.0]], [[1, 0]], onehot, 2)
    >>> ds.phi[0, 0], ds.next_phi[0, 0, 1]
    (array([0., 1., 0., 0.]), array([0., 0., 0., 1.]))
    """
    _check_feature_map(feature_map, n_actions)
    states = as_array(states, "states")
    next_states = as_array(next_states, "next_states")
    actions_arr = as_array(actions, "actions")
    if actions_arr.ndim != 2:
        raise ValueError(f"actions must have shape (K, H), got {actions_arr.shape}")
    actions_arr = as_index_array(actions_arr, "actions", int(n_actions), ndim=2)
    K, H = actions_arr.shape
    if states.shape[:2] != (K, H) or next_states.shape[:2] != (K, H):
        raise ValueError(
            f"states and next_states must start with (K, H) = {(K, H)} like actions, got "
            f"{states.shape} and {next_states.shape}"
        )
    if ((actions_arr < 0) | (actions_arr >= n_actions)).any():
        raise ValueError(f"actions must lie in [0, {n_actions}); got values outside")
    flat_s = states.reshape((K * H,) + states.shape[2:])
    flat_ns = next_states.reshape((K * H,) + next_states.shape[2:])
    phi = np.asarray(feature_map(flat_s, actions_arr.reshape(-1)), dtype=float)
    if phi.ndim != 2 or phi.shape[0] != K * H:
        raise ValueError(f"feature_map must return (n, d) = ({K * H}, d), got {phi.shape}")
    d = phi.shape[1]
    next_phi = np.empty((K * H, n_actions, d))
    for a in range(n_actions):
        out = np.asarray(feature_map(flat_ns, np.full(K * H, a)), dtype=float)
        if out.shape != (K * H, d):
            raise ValueError(f"feature_map returned shape {out.shape} for the next states")
        next_phi[:, a] = out
    if callable(next_values):
        nv = np.asarray(next_values(flat_ns), dtype=float)
        if nv.shape != (K * H, n_actions):
            raise ValueError(
                f"next_values(next_states) must return (n, A) = {(K * H, n_actions)}, "
                f"got {nv.shape}"
            )
        next_values = nv.reshape(K, H, n_actions)
    return cls.from_features(
        phi.reshape(K, H, d),
        rewards,
        next_phi.reshape(K, H, n_actions, d),
        next_values,
        check_simplex=check_simplex,
        states=states,
        actions=actions_arr,
        next_states=next_states,
    )



def _check_finite_observations(field, name: str, horizon: int) -> None:
    """Refuse NaN or infinite observations (a step at a time: memory maps stay unread but
    for one chunk), naming the step and trajectory: a feature map would turn them into
    features the fit cannot use, and the error would blame the map."""
    if field.dtype.kind != "f":
        return
    for h in range(horizon):
        for s, _, rows in field.chunks(h, _st.CHUNK):
            bad = ~np.isfinite(rows)
            if bad.any():
                k = s + int(np.argwhere(bad)[0][0])
                raise ValueError(f"{name} holds a non-finite value at step {h}, trajectory {k} "
                                 f"({name}[{k}, {h}]): clean the observations first")
