"""The paper's suboptimality gap ``SubOpt(pi, s, lam) = V_1^{*,lam}(s) - V_1^{pi,lam}(s)``."""

from __future__ import annotations

import numbers

from .dynamic_programming import robust_values

__all__ = ["suboptimality"]


def suboptimality(env, policy, divergence, lam, state=None) -> float:
    """``V_0^{*,lam}(s) - V_0^{pi,lam}(s)`` (the paper's eq. (suboptimality), 0-based steps).

    Parameters
    ----------
    env : FiniteLinearMDP
    policy
        Any policy form accepted by :func:`r2pvi.envs.policies.policy_table` (a fitted
        estimator acts greedily on its Q-values).
    divergence : {"tv", "kl", "chi2", "hellinger"}, dict or FDivergence
    lam : float > 0
    state : int, optional
        The state ``s``; None averages over the initial distribution (the initial state
        when it is fixed, as in the simulated linear MDP). Every per-state gap is >= 0.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.evaluation import optimal_policy, suboptimality
    >>> env = SimulatedLinearMDP()
    >>> suboptimality(env, optimal_policy(env, "kl", 0.3), "kl", 0.3)
    0.0
    >>> bool(suboptimality(env, "uniform", "kl", 0.3) > 0)
    True
    """
    _, v_star = robust_values(env, divergence, lam)
    _, v_pi = robust_values(env, divergence, lam, policy)
    gap = v_star[0] - v_pi[0]
    if state is None:
        return float(env.initial @ gap)
    if isinstance(state, bool) or not isinstance(state, numbers.Integral):
        raise TypeError(f"state must be an integer state index, got {state!r}")
    if not 0 <= state < env.n_states:
        raise ValueError(f"state must lie in [0, {env.n_states}), got {state}")
    return float(gap[state])
