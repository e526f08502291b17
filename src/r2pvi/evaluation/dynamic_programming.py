"""Exact dynamic programming on finite linear MDPs, reusing the duals with the true factors.

Every value function here is one backward induction: ``V_H = 0`` and, for
``h = H-1, ..., 0``,

    Q_h(s, a) = r_h(s, a) + sum_i phi_i(s, a) w_{h,i},   w_h = dual(E_h, V_{h+1}),

with ``E_h = FactorExpectation(mu_h)`` the exact expectation under the true factor
distributions, and ``V_h(s) = max_a Q_h(s, a)`` (optimal) or ``sum_a pi_h(a|s) Q_h(s, a)``
(a given policy). The dual is ``E_h`` itself for nominal values, the regularized duals of
:mod:`r2pvi.duals.regularized` for robust-regularized values (Prop. 3.1 and 4.1 of the
paper) and the constrained duals of ``r2pvi.duals.constrained`` for TV/KL balls. Nothing is
re-derived here: the code that learns and the code that evaluates share the formulas.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np

from .._validation import as_float_array, check_scalar
from ..duals.constrained import kl_constrained, tv_constrained
from ..duals.fdivergence import CHI2, KL, TV, FDivergence, get_divergence
from ..duals.general_f import f_regularized
from ..duals.operator import FactorExpectation
from ..duals.regularized import chi2_regularized, kl_regularized, tv_regularized
from ..envs.finite import FiniteLinearMDP
from ..envs.policies import policy_table

__all__ = [
    "nominal_values",
    "robust_values",
    "constrained_values",
    "greedy_policy",
    "optimal_policy",
    "regularized_step",
    "finite_backward",
]

#: ``step(h, E, v) -> w``: the weights of step ``h`` from the next values ``v`` over all states.
StepWeights = Callable[[int, FactorExpectation, np.ndarray], np.ndarray]


def _check_finite_env(env, func: str) -> FiniteLinearMDP:
    if not isinstance(env, FiniteLinearMDP):
        raise TypeError(
            f"{func} needs a finite linear MDP with explicit factors (FiniteLinearMDP, "
            f"SimulatedLinearMDP, HardInstance), got {type(env).__name__}; the American put "
            "option has no factor model: use expected_return or monte_carlo_return"
        )
    return env


# Per environment (held weakly; its factors, features and rewards never change): the exact
# expectation operators of its steps and its optimal robust-regularized values, which
# suboptimality gaps, optimal policies and the uncertainty term all start from.
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _env_cache(env) -> dict:
    try:
        return _CACHE.setdefault(env, {})
    except TypeError:  # not weakly referable or not hashable: no cache
        return {}


def _expectations(env: FiniteLinearMDP) -> list[FactorExpectation]:
    """``FactorExpectation(mu_h)`` for every step (built and validated once per env)."""
    cache = _env_cache(env)
    if "E" not in cache:
        cache["E"] = [FactorExpectation(env.mu[h]) for h in range(env.horizon)]
    return cache["E"]


def finite_backward(env: FiniteLinearMDP, step: StepWeights, policy=None, rewards=None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(Q (H, S, A), V (H+1, S))`` of the backward induction with weights ``step(h, E, v)``.

    ``rewards (H, S, A)`` defaults to the environment's reward table; other per-step costs
    (e.g. the penalty bonuses of :func:`r2pvi.theory.uncertainty_values`) reuse the same loop.
    ``policy`` None maximizes over actions; otherwise any form of
    :func:`r2pvi.envs.policies.policy_table`.
    """
    H, S, A = env.horizon, env.n_states, env.n_actions
    pi = None if policy is None else policy_table(env, policy)
    rewards = env.reward_table if rewards is None else rewards
    Q = np.empty((H, S, A))
    V = np.zeros((H + 1, S))
    operators = _expectations(env)
    for h in range(H - 1, -1, -1):
        w = np.asarray(step(h, operators[h], V[h + 1]), dtype=float)
        Q[h] = rewards[h] + env.features(h) @ w
        V[h] = Q[h].max(axis=1) if pi is None else np.einsum("sa,sa->s", pi[h], Q[h])
    return Q, V


def resolve_divergence(divergence) -> FDivergence:
    """The :class:`~r2pvi.FDivergence` of a name, parameter dict or object."""
    if not isinstance(divergence, str | dict | FDivergence):
        raise TypeError(
            "divergence must be 'tv', 'kl', 'chi2', 'hellinger', a parameter dict or an "
            f"FDivergence, got {divergence!r}"
        )
    return get_divergence(divergence)


def regularized_step(divergence, lam: float) -> StepWeights:
    """``(h, E, v) -> w``: the regularized dual of ``divergence`` at ``lam``.

    TV, KL and chi^2 (by name or as the built-in objects) use their closed-form / exact
    duals; any other f-divergence uses the general dual (Algorithm 1) with
    :func:`~r2pvi.duals.f_regularized`. ``v`` covers every state, so the minimum that TV and
    linearly growing f need is the minimum over all states (mass can move anywhere).
    """
    div = resolve_divergence(divergence)
    lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
    if div is TV:
        return lambda h, E, v: tv_regularized(E, v, lam, v_min=float(np.min(v)))
    if div is KL:
        return lambda h, E, v: kl_regularized(E, v, lam)
    if div is CHI2:
        return lambda h, E, v: chi2_regularized(E, v, lam)
    return lambda h, E, v: f_regularized(E, v, lam, div, v_min=float(np.min(v)))


def nominal_values(env, policy=None) -> tuple[np.ndarray, np.ndarray]:
    """Nominal (non-robust) ``Q (H, S, A)`` and ``V (H + 1, S)``.

    Optimal when ``policy`` is None, else the values of ``policy`` (any form accepted by
    :func:`r2pvi.envs.policies.policy_table`). ``V[H] = 0``.

    Examples
    --------
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.evaluation import nominal_values
    >>> Q, V = nominal_values(SimulatedLinearMDP())
    >>> round(float(V[0, 0]), 6), int(Q[0, 0].argmax())    # value at x1, best action
    (1.62425, 15)
    """
    env = _check_finite_env(env, "nominal_values")
    return finite_backward(env, lambda h, E, v: E(v), policy)


def robust_values(env, divergence, lam, policy=None) -> tuple[np.ndarray, np.ndarray]:
    """Robust-regularized ``Q^{pi,lam} (H, S, A)`` and ``V^{pi,lam} (H + 1, S)``.

    The optimal ``Q^{*,lam}``, ``V^{*,lam}`` when ``policy`` is None (the optimal policy is
    deterministic: :func:`optimal_policy`). Uses the true factors of ``env``.

    Parameters
    ----------
    env : FiniteLinearMDP
    divergence : {"tv", "kl", "chi2", "hellinger"}, dict or FDivergence
    lam : float > 0
        Regularization strength; smaller is more robust.
    policy : policy, optional

    Examples
    --------
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.evaluation import robust_values
    >>> Q, V = robust_values(SimulatedLinearMDP(), "tv", lam=0.3)
    >>> V.shape, round(float(V[0, 0]), 6)
    ((4, 5), 0.29985)
    """
    env = _check_finite_env(env, "robust_values")
    step = regularized_step(divergence, lam)
    div = resolve_divergence(divergence)
    if policy is not None or not any(div is d for d in (TV, KL, CHI2)):
        return finite_backward(env, step, policy)
    # The optimal values are computed once per (env, divergence, lam) and copied out.
    cache = _env_cache(env)
    key = ("robust", div.name, float(lam))
    if key not in cache:
        cache[key] = finite_backward(env, step)
    Q, V = cache[key]
    return Q.copy(), V.copy()


def constrained_values(env, divergence, rho, policy=None) -> tuple[np.ndarray, np.ndarray]:
    """Robust values over d-rectangular TV or KL balls of radius ``rho`` (the DRMDP values).

    ``w_{h,i} = inf_{D(mu || mu_{h,i}) <= rho_{h,i}} E_mu V_{h+1}``, through
    ``tv_constrained`` and ``kl_constrained`` of ``r2pvi.duals.constrained``.

    Parameters
    ----------
    env : FiniteLinearMDP
    divergence : {"tv", "kl"}
    rho : float, array (d,) or array (H, d)
        Radii (>= 0), per factor and step.
    policy : policy, optional
        None: the optimal robust values.
    """
    env = _check_finite_env(env, "constrained_values")
    div = resolve_divergence(divergence)
    if div is not TV and div is not KL:
        raise ValueError(
            f"constrained_values supports the 'tv' and 'kl' balls, got {div.name!r}"
        )
    radii = _as_radii(rho, env.horizon, env.n_features)
    dual = tv_constrained if div is TV else kl_constrained

    def step(h, E, v):
        if div is TV:
            return dual(E, v, radii[h], v_min=float(np.min(v)))
        return dual(E, v, radii[h])

    return finite_backward(env, step, policy)


def _as_radii(rho, H: int, d: int) -> np.ndarray:
    arr = as_float_array(rho, "rho")
    if arr.ndim == 0:
        arr = np.full((H, d), float(arr))
    elif arr.shape == (d,):
        arr = np.tile(arr, (H, 1))
    elif arr.shape != (H, d):
        raise ValueError(
            f"rho must be a scalar, a (d,) = ({d},) or an (H, d) = {(H, d)} array, got shape "
            f"{arr.shape}"
        )
    if (arr < 0).any():
        raise ValueError("rho must be >= 0 (the radius of each factor's ball)")
    return arr


def greedy_policy(Q: np.ndarray, rtol: float = 1e-12) -> np.ndarray:
    """Greedy action indices ``(H, S)`` of ``Q (H, S, A)``.

    Actions within ``rtol * (1 + |max Q|)`` of the best count as ties, and ties go to the
    lowest index (as the estimators' ``act``), so round-off does not pick the action.
    """
    Q = np.asarray(Q, dtype=float)
    best = Q.max(axis=-1, keepdims=True)
    return np.argmax(Q >= best - rtol * (1.0 + np.abs(best)), axis=-1)


def optimal_policy(env, divergence=None, lam=None) -> np.ndarray:
    """The optimal deterministic policy ``(H, S)``: nominal (``divergence=None``) or
    robust-regularized (``divergence`` and ``lam``).

    Examples
    --------
    >>> from r2pvi.envs import HardInstance
    >>> from r2pvi.evaluation import optimal_policy
    >>> env = HardInstance(d=3, H=2, lam=0.5, epsilon=0.1, delta=0.3, xi=[1, -1, 1])
    >>> optimal_policy(env, "kl", 0.5)[:, 0].tolist(), env.optimal_actions.tolist()
    ([5, 5], [5, 5])
    """
    if divergence is None:
        if lam is not None:
            raise ValueError("lam given without a divergence: pass divergence= as well")
        Q, _ = nominal_values(env)
    else:
        if lam is None:
            raise ValueError("a divergence needs its regularization strength lam")
        Q, _ = robust_values(env, divergence, lam)
    return greedy_policy(Q)
