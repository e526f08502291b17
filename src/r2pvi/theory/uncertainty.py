"""The instance-dependent uncertainty term of the paper's upper and lower bounds, exactly.

Theorem "instance-dependent upper bounds" (Section 5) bounds the suboptimality of R2PVI by
``2 beta`` times

    sup_{P in U^lam(P0)} sum_h E^{pi*,P}[sum_i ||phi_i(s_h, a_h) 1_i||_{Lambda_h^{-1}} | s_0 = s],

and Theorem "lower bound" shows the term is intrinsic. ``U^lam(P0)`` is the robustly
admissible set: a product over ``(h, s, a)`` of
``{sum_i phi_i(s, a) mu_{h,i} : D(mu_{h,i} || mu0_{h,i}) <= max_s V*_{h+1}(s) / lam}``.
Because the set is a product over ``(h, s, a)`` and, inside it, over the factors ``i``
(chosen independently), and ``phi >= 0``, the supremum is the backward dynamic program

    U_H = 0,
    U_h(s) = sum_a pi*_h(a|s) [c_h(s, a) + sum_i phi_i(s, a) w_{h,i}],
    w_{h,i} = sup {E_mu U_{h+1} : D(mu || mu0_{h,i}) <= rho_h},

with ``c_h(s, a) = sum_i phi_i(s, a) sqrt([Lambda_h^{-1}]_ii)`` (the "l1" penalty of the
theorem with ``beta = 1``). The supremum over each ball is ``-inf {E_mu[-U] : ...}``: the
constrained duals of :mod:`r2pvi.duals.constrained` (TV, KL and chi^2 balls) applied with the
true factors, ``FactorExpectation(mu_h)``. Nothing is re-derived here. Steps are 0-based.
"""

from __future__ import annotations

import numbers

import numpy as np

from .._validation import as_float_array, check_scalar
from ..duals.constrained import chi2_constrained, kl_constrained, tv_constrained
from ..duals.fdivergence import CHI2, KL, TV
from ..envs.finite import FiniteLinearMDP
from ..envs.policies import policy_table

__all__ = [
    "admissible_radii",
    "ball_sup",
    "bonus_table",
    "uncertainty_values",
    "uncertainty_term",
]

_BALLS = {"tv": tv_constrained, "kl": kl_constrained, "chi2": chi2_constrained}


def _divergence_name(divergence) -> str:
    """'tv', 'kl' or 'chi2' from a name or the built-in objects; anything else raises."""
    if isinstance(divergence, str) and divergence.lower() in _BALLS:
        return divergence.lower()
    for name, builtin in (("tv", TV), ("kl", KL), ("chi2", CHI2)):
        if divergence is builtin:
            return name
    raise ValueError(
        "the robustly admissible set is defined for the theorem's divergences 'tv', 'kl' and "
        f"'chi2', got {divergence!r}"
    )


def admissible_radii(v_star: np.ndarray, lam: float) -> np.ndarray:
    """Radii ``rho_h = max_s V*_{h+1}(s) / lam`` of the robustly admissible set, ``(H,)``.

    Paper, Thm. instance-dependent upper bounds, definition of ``U_h^lam(s, a; mu0_h)``.

    Parameters
    ----------
    v_star : ndarray (H + 1, S)
        Optimal robust-regularized values (``V*[H] = 0``), e.g. from
        :func:`r2pvi.evaluation.robust_values`.
    lam : float > 0

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.theory import admissible_radii
    >>> admissible_radii(np.array([[2.0, 1.5], [1.0, 0.5], [0.0, 0.0]]), lam=0.5)
    array([2., 0.])
    """
    v_star = as_float_array(v_star, "v_star", ndim=2)
    lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
    return np.maximum(v_star[1:].max(axis=1), 0.0) / lam


def ball_sup(divergence, E, u: np.ndarray, rho) -> np.ndarray:
    """``sup {E_mu u : D(mu || mu0_i) <= rho_i}`` for every factor ``i``: ``-inf E_mu[-u]``.

    The constrained duals of :mod:`r2pvi.duals.constrained` (``tv_constrained``,
    ``kl_constrained``, ``chi2_constrained``) applied to ``-u``. Under TV the mass may move
    to any of the operator's points (every state, for a ``FactorExpectation``); under KL and
    chi^2 it stays on the support of ``mu0_i``.

    Parameters
    ----------
    divergence : {"tv", "kl", "chi2"}
    E : ExpectationOperator
        Rows ``mu0_i``; a :class:`~r2pvi.duals.FactorExpectation` for exact evaluation.
    u : ndarray (n,)
    rho : float or ndarray (d,)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation
    >>> from r2pvi.theory import ball_sup
    >>> E = FactorExpectation(np.array([[0.5, 0.5, 0.0]]))
    >>> u = np.array([0.0, 1.0, 4.0])
    >>> ball_sup("tv", E, u, 0.25)     # move 1/4 of the mass from u = 0 to u = 4
    array([1.5])
    >>> ball_sup("chi2", E, u, 3.0)    # chi^2 keeps the support: at most max(0, 1) = 1
    array([1.])
    """
    dual = _BALLS[_divergence_name(divergence)]
    return -dual(E, -np.asarray(u, dtype=float), rho)


def _inverse_diagonal(estimator, H: int, d: int) -> np.ndarray:
    inv = getattr(estimator, "gram_inv_diag_", None)
    if inv is None:
        if callable(getattr(estimator, "fit", None)):
            from .._compat import not_fitted_error

            raise not_fitted_error()(
                f"this {type(estimator).__name__} is not fitted yet; call fit(dataset) first"
            )
        inv = estimator
    inv = as_float_array(inv, "gram_inv_diag")
    if inv.shape != (H, d):
        raise ValueError(
            f"the Gram inverse diagonals must have shape (H, d) = {(H, d)} to match the "
            f"environment, got {inv.shape}"
        )
    if (inv < 0).any():
        raise ValueError("the diagonal of Lambda_h^{-1} must be >= 0")
    return inv


def bonus_table(env, estimator) -> np.ndarray:
    """``c_h(s, a) = sum_i phi_i(s, a) ||1_i||_{Lambda_h^{-1}}``, ``(H, S, A)``.

    The summand of the uncertainty term, ``sum_i ||phi_i(s, a) 1_i||_{Lambda_h^{-1}}``
    (paper, Thm. instance-dependent upper bounds), i.e. the "l1" penalty with ``beta = 1``.

    Parameters
    ----------
    env : FiniteLinearMDP
    estimator : fitted estimator or ndarray (H, d)
        Anything with ``gram_inv_diag_`` (``diag(Lambda_h^{-1})``), or that array itself.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.theory import bonus_table
    >>> env = SimulatedLinearMDP()
    >>> c = bonus_table(env, np.full((3, 4), 0.04))   # Lambda_h^{-1} = 0.04 I
    >>> c.shape, float(c[0, 0, 0])                     # sum_i phi_i * 0.2
    ((3, 5, 16), 0.2)
    """
    env = _check_env(env)
    inv = _inverse_diagonal(estimator, env.horizon, env.n_features)
    scale = np.sqrt(inv)
    return np.stack([env.features(h) @ scale[h] for h in range(env.horizon)])


def _check_env(env) -> FiniteLinearMDP:
    from ..evaluation.dynamic_programming import _check_finite_env

    return _check_finite_env(env, "the uncertainty term")


def uncertainty_values(env, estimator, divergence, lam, *, policy=None) -> np.ndarray:
    """``U_h(s)``, the worst case over ``U^lam(P0)`` of the remaining uncertainty, ``(H+1, S)``.

    ``U[h, s] = sup_{P in U^lam(P0)} sum_{t >= h} E^{pi, P}[c_t(s_t, a_t) | s_h = s]`` with
    ``c_t`` from :func:`bonus_table`, by the backward dynamic program of the module
    docstring; ``U[0]`` is the paper's term for every start state, ``U[H] = 0``.

    Parameters
    ----------
    env : FiniteLinearMDP
    estimator : fitted estimator or ndarray (H, d)
        Provides ``diag(Lambda_h^{-1})`` (``gram_inv_diag_``).
    divergence : {"tv", "kl", "chi2"}
    lam : float > 0
    policy : policy, optional
        The policy ``pi`` of the expectation; None is the paper's ``pi*``, the exact
        robust-regularized optimal policy (:func:`r2pvi.evaluation.optimal_policy`, ties to
        the lowest action). Any form accepted by :func:`r2pvi.envs.policies.policy_table`.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.theory import uncertainty_values
    >>> U = uncertainty_values(SimulatedLinearMDP(), np.full((3, 4), 0.01), "tv", lam=1.0)
    >>> U.shape, U[0, 0].round(6)       # 0.1 per step: the features sum to 1
    ((4, 5), np.float64(0.3))
    """
    from ..evaluation import optimal_policy, robust_values
    from ..evaluation.dynamic_programming import finite_backward

    env = _check_env(env)
    name = _divergence_name(divergence)
    lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
    costs = bonus_table(env, estimator)
    _, v_star = robust_values(env, name, lam)
    radii = admissible_radii(v_star, lam)
    pi = policy_table(env, optimal_policy(env, name, lam) if policy is None else policy)
    # The evaluation layer's backward induction with the bonuses as costs and the sup over
    # each factor's ball as the step weights.
    _, U = finite_backward(env, lambda h, E, v: ball_sup(name, E, v, radii[h]), pi, costs)
    return U


def uncertainty_term(env, estimator, divergence, lam, state=None, *, policy=None) -> float:
    """The paper's ``sup_{P in U^lam(P0)} sum_h E^{pi*,P}[sum_i ||phi_i(s,a) 1_i||_{Lambda_h^{-1}}
    | s_1 = s]``, exactly.

    Thm. instance-dependent upper bounds: ``SubOpt(pi_hat, s, lam) <= 2 beta`` times this term
    (with probability ``>= 1 - delta`` for the theorem's beta); Thm. lower bound: no
    algorithm beats a constant times it. Computed by :func:`uncertainty_values` with the
    fitted estimator's Gram matrices.

    Parameters
    ----------
    env : FiniteLinearMDP
    estimator : fitted estimator or ndarray (H, d)
        Provides ``diag(Lambda_h^{-1})`` (``gram_inv_diag_``).
    divergence : {"tv", "kl", "chi2"}
    lam : float > 0
    state : int, optional
        The start state ``s``; None averages over the initial distribution (the start
        state when it is fixed), as :func:`r2pvi.evaluation.suboptimality` does.
    policy : policy, optional
        None: the exact robust-regularized optimal policy ``pi*``.

    Examples
    --------
    >>> from r2pvi import R2PVI
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.theory import uncertainty_term
    >>> env = SimulatedLinearMDP()
    >>> est = R2PVI("kl", lam=1.0, beta=0.1).fit(env.collect(1000, seed=0))
    >>> round(uncertainty_term(env, est, "kl", lam=1.0), 4)
    0.3852
    """
    U = uncertainty_values(env, estimator, divergence, lam, policy=policy)
    if state is None:
        return float(env.initial @ U[0])
    if isinstance(state, bool) or not isinstance(state, numbers.Integral):
        raise TypeError(f"state must be an integer state index, got {state!r}")
    if not 0 <= state < env.n_states:
        raise ValueError(f"state must lie in [0, {env.n_states}), got {state}")
    return float(U[0, state])
