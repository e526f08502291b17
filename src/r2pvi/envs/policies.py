"""Policies in finite models: every accepted form becomes one ``(H, S, A)`` probability table.

A policy for a finite linear MDP may be

- an ``(H, S)`` array of action indices (deterministic);
- an ``(H, S, A)`` array of action probabilities (stochastic);
- a fitted estimator (anything with ``act(phi_all, h, known_values)``, such as
  :class:`r2pvi.R2PVI`): it acts greedily on its Q-values at every ``(h, s)``, with the
  environment's known values (absorbing fail states) passed along as in the dataset;
- a vectorized callable ``policy(h, states) -> actions`` (integer states and actions);
- the strings ``"uniform"`` and ``"behavior"`` (the environment's behaviour policy).
"""

from __future__ import annotations

import numbers

import numpy as np

from .._validation import as_index_array

__all__ = ["policy_table", "is_estimator"]


def is_estimator(policy) -> bool:
    """Whether ``policy`` is a fitted-estimator-like object (has ``act`` and ``q_values``)."""
    return callable(getattr(policy, "act", None)) and callable(getattr(policy, "q_values", None))


def policy_table(env, policy, name: str = "policy") -> np.ndarray:
    """The ``(H, S, A)`` action-probability table of ``policy`` in the finite model ``env``.

    Parameters
    ----------
    env : FiniteLinearMDP
        Provides ``horizon``, ``n_states``, ``n_actions``, ``features(h)``,
        ``known_values`` and ``behavior_policy``.
    policy : array_like, estimator, callable or str
        See the module docstring.
    name : str
        Argument name used in error messages.

    Returns
    -------
    ndarray (H, S, A)
        Rows are probability distributions over actions.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.envs.policies import policy_table
    >>> env = SimulatedLinearMDP()
    >>> table = policy_table(env, np.full((3, 5), 15))    # always a = (1, 1, 1, 1)
    >>> table.shape, float(table[0, 0, 15])
    ((3, 5, 16), 1.0)
    """
    H, S, A = env.horizon, env.n_states, env.n_actions
    if isinstance(policy, str):
        key = policy.lower()
        if key == "uniform":
            return np.full((H, S, A), 1.0 / A)
        if key in ("behavior", "behaviour"):
            return np.array(env.behavior_policy, dtype=float)
        raise ValueError(
            f"{name} must be 'uniform', 'behavior', an (H, S) array of actions, an (H, S, A) "
            f"array of probabilities, a fitted estimator or a callable; got the string {policy!r}"
        )
    if is_estimator(policy):
        return _one_hot(_estimator_actions(env, policy, name), A)
    if callable(policy):
        actions = np.empty((H, S), dtype=np.int64)
        states = np.arange(S)
        for h in range(H):
            out = np.asarray(policy(h, states))
            if out.shape != (S,):
                raise ValueError(
                    f"{name}(h, states) must return one action per state, shape ({S},); "
                    f"got shape {out.shape} at h={h}"
                )
            actions[h] = _as_actions(out, A, name)
        return _one_hot(actions, A)
    arr = np.asarray(policy)
    if arr.dtype == bool or arr.dtype.kind not in "iuf":
        raise TypeError(
            f"{name} must be an integer (H, S) array of action indices or a float (H, S, A) "
            f"array of probabilities, got dtype {arr.dtype}"
        )
    if arr.ndim == 2:
        if arr.shape != (H, S):
            raise ValueError(
                f"{name} as action indices must have shape (H, S) = {(H, S)}, got {arr.shape}"
            )
        return _one_hot(_as_actions(arr, A, name), A)
    if arr.ndim == 3:
        if arr.shape != (H, S, A):
            raise ValueError(
                f"{name} as probabilities must have shape (H, S, A) = {(H, S, A)}, "
                f"got {arr.shape}"
            )
        probs = arr.astype(float)
        if not np.isfinite(probs).all() or (probs < -1e-12).any():
            raise ValueError(f"{name} probabilities must be finite and non-negative")
        sums = probs.sum(axis=2)
        if not np.allclose(sums, 1.0, atol=1e-8):
            worst = np.unravel_index(np.argmax(np.abs(sums - 1.0)), sums.shape)
            raise ValueError(
                f"{name}[h, s] must sum to 1 over actions; (h, s) = {tuple(map(int, worst))} "
                f"sums to {sums[worst]:.6g}: normalize it with policy / policy.sum(-1, "
                "keepdims=True)"
            )
        return np.maximum(probs, 0.0) / sums[..., None]
    raise ValueError(
        f"{name} must be an (H, S) array of action indices or an (H, S, A) array of "
        f"probabilities with (H, S, A) = {(H, S, A)}; got an array of shape {arr.shape}"
    )


def _as_actions(arr: np.ndarray, n_actions: int, name: str) -> np.ndarray:
    return as_index_array(arr, f"{name} action indices", n_actions)


def _one_hot(actions: np.ndarray, n_actions: int) -> np.ndarray:
    return (actions[..., None] == np.arange(n_actions)).astype(float)


def _estimator_actions(env, estimator, name: str) -> np.ndarray:
    """Greedy actions ``(H, S)`` of a fitted estimator at every state of ``env``."""
    H = env.horizon
    horizon = getattr(estimator, "horizon_", None)
    n_features = getattr(estimator, "n_features_in_", None)
    if horizon is None:
        raise ValueError(
            f"{name} is an unfitted {type(estimator).__name__}: call fit(env.collect(...)) first"
        )
    if horizon != H or n_features != env.n_features:
        raise ValueError(
            f"{name} was fitted with horizon {horizon} and {n_features} features, but the "
            f"environment has H = {H} and d = {env.n_features}: fit it on a dataset of this "
            "environment"
        )
    known = env.known_values
    known = None if np.isnan(known).all() else known
    actions = np.empty((H, env.n_states), dtype=np.int64)
    for h in range(H):
        actions[h] = estimator.act(env.features(h), h, known_values=known)
    return actions


def check_step(h, horizon: int) -> int:
    """A 0-based step index in ``[0, horizon)``."""
    if isinstance(h, bool) or not isinstance(h, numbers.Integral):
        raise TypeError(f"h must be an integer step in [0, {horizon}), got {h!r}")
    if not 0 <= h < horizon:
        raise ValueError(f"h must be a 0-based step in [0, {horizon}), got {h}")
    return int(h)
