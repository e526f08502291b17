"""Duals of the regularized problem ``inf_mu E_mu V + lam D(mu || mu0)``, one per factor.

Every function takes an expectation operator ``E`` (d factors over n points), the values
``v (n,)`` at those points and ``lam > 0``, and returns the d dual values ``w (d,)``.
With a :class:`~r2pvi.duals.RidgeExpectation` they are the paper's estimators; with a
:class:`~r2pvi.duals.FactorExpectation` they are the exact robust-regularized expectations.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from .fdivergence import FDivergence
from .operators import ExpectationOperator
from .piecewise import blockwise_max, dense_max

__all__ = ["tv_regularized", "kl_regularized", "chi2_regularized", "f_regularized"]

_TINY = 1e-250


def tv_regularized(E: ExpectationOperator, v: np.ndarray, lam: float, v_min=None) -> np.ndarray:
    """TV: ``E_i[ [V]_{V_min + lam} ]`` (paper, Prop. TV duality and eq. (TV-estimation)).

    ``v_min`` is the minimum of V over the whole state space (mass can move anywhere under
    TV); None takes the minimum of ``v``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, tv_regularized
    >>> E = FactorExpectation(np.array([[0.5, 0.5, 0.0]]))
    >>> tv_regularized(E, np.array([1.0, 3.0, 0.0]), lam=0.5)   # E[min(V, 0 + 0.5)]
    array([0.5])
    """
    floor = np.min(v) if v_min is None else v_min
    return E(np.minimum(v, floor + lam))


def kl_regularized(E: ExpectationOperator, v: np.ndarray, lam: float, v_max=None) -> np.ndarray:
    """KL: ``-lam log max{E_i[exp(-V/lam)], exp(-V_max/lam)}`` (paper, eq. (KL-estimation)).

    ``v_max`` is the upper bound on V whose ``exp(-V_max/lam)`` floors the (ridge)
    estimate, ``H`` in the paper; None takes the maximum of ``v``. Computed in the log
    domain, shifted by the minimum value, so it is finite and exact for ``lam`` from 1e-3 to
    1e3 and beyond; factors whose shifted estimate underflows are recomputed by a
    sign-aware log-sum-exp over their explicit weights.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, kl_regularized
    >>> E = FactorExpectation(np.array([[0.5, 0.5]]))
    >>> kl_regularized(E, np.array([0.0, 3.0]), lam=1e-3)   # -> min V as lam -> 0
    array([0.00069315])
    """
    v = np.asarray(v, dtype=float)
    upper = np.max(v) if v_max is None else v_max
    shift = np.min(v)
    with np.errstate(under="ignore"):
        u = E(np.exp(-(v - shift) / lam))
    log_floor = -(upper - shift) / lam
    # A clearly negative (ridge) estimate gets the floor; only estimates too small in magnitude
    # to trust after the global shift are recomputed exactly in the log domain.
    small = np.abs(u) < _TINY
    log_u = np.full_like(u, -np.inf)
    np.log(u, out=log_u, where=u >= _TINY)
    if small.any():
        dims = np.flatnonzero(small)
        rows = E.rows(dims)
        # A factor with no weight at all (e.g. a feature no sample activates) keeps -inf and
        # gets the floor; only factors with weight need the exact log-sum-exp.
        live = np.any(rows != 0.0, axis=1)
        if live.any():
            lse, sign = logsumexp(-(v - shift) / lam, b=rows[live], axis=1, return_sign=True)
            log_u[dims[live]] = np.where(sign > 0, lse, -np.inf)
    return shift - lam * np.maximum(log_u, log_floor)


def chi2_regularized(
    E: ExpectationOperator,
    v: np.ndarray,
    lam: float,
    mean_clip: tuple[float, float] | None = None,
    second_clip: tuple[float, float] | None = None,
    method: str = "auto",
) -> np.ndarray:
    """chi^2: ``max_alpha E_i[V]_alpha + (E_i[V]_alpha)^2/(4 lam) - E_i[V^2]_alpha/(4 lam)``.

    The paper's eq. (parameter estimation x2), maximized exactly over ``alpha`` in
    ``[min v, max v]`` for each factor, with the optional clipping of the first and second
    moment estimates to ``mean_clip = (0, H)`` and ``second_clip = (0, H^2)``
    (eqs. (estimation of EV / EV2 in chi2)). With a true-model operator and no clipping this
    is ``max_alpha E[V]_alpha - Var[V]_alpha / (4 lam)`` (Prop. chi^2 duality).

    The objective is piecewise quadratic in ``alpha``; every breakpoint (sorted value), every
    point where a clip becomes active and the stationary point of every piece are candidates
    (:mod:`r2pvi.duals.piecewise`). ``method="dense"`` evaluates all of them from prefix sums
    over the sorted values; ``"blockwise"`` gives the same exact maximum by branch and bound
    over blocks of 16 breakpoints (faster for large n); ``"auto"`` picks blockwise from 512
    values on.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, chi2_regularized
    >>> E = FactorExpectation(np.array([[0.5, 0.5]]))
    >>> chi2_regularized(E, np.array([0.0, 2.0]), lam=1e6).round(4)   # lam -> inf: E[V]
    array([1.])
    """
    v = np.asarray(v, dtype=float)
    lo_v, hi_v = float(np.min(v)), float(np.max(v))
    # E([V]^2_alpha) = C + B alpha^2 is monotone on a segment that does not contain alpha = 0.
    extra = (0.0,) if lo_v < 0.0 < hi_v else ()
    if method == "auto":
        method = "blockwise" if v.size >= 512 else "dense"
    if method == "dense":
        return dense_max(E, v, lam, mean_clip, second_clip, extra)
    if method == "blockwise":
        return blockwise_max(E, v, lam, mean_clip, second_clip, extra)
    raise ValueError(f"method must be 'auto', 'dense' or 'blockwise', got {method!r}")


def f_regularized(
    E: ExpectationOperator,
    v: np.ndarray,
    lam: float,
    divergence: FDivergence,
    v_min=None,
    xtol: float = 1e-11,
    max_iter: int = 300,
) -> np.ndarray:
    """General f: ``sup_alpha alpha - lam E_i[f*((alpha - V)/lam)]`` (paper, Algorithm 1).

    Solved per factor by a vectorized golden-section search on the bracket
    ``[V_min + lam*lo, min(V_max + lam*hi, V_min + lam*dom)]``, where ``[lo, hi]`` is the
    subdifferential of f at 1 and ``dom`` the right end of the conjugate's domain; the
    bracket holds the maximizer of the exact (concave) dual. The search is safeguarded:
    non-finite objective values count as ``-inf``, both bracket ends are evaluated and the
    best point seen is returned (the ridge-estimated objective need not be concave).

    ``v_min`` is the minimum of V over all states (it matters only when f grows linearly,
    e.g. TV and Hellinger); None takes the minimum of ``v``.

    With a true-model operator this equals the closed forms (TV, KL, chi^2). With a ridge
    operator it is Algorithm 1 as written: ridge shrinkage makes the weights of a factor sum
    to less than 1 while the ``alpha`` term is not shrunk, so it differs from the closed-form
    estimators (which shrink everything) by ``(1 - sum_j M_ij) alpha*``; the difference
    vanishes as K grows or ``gamma -> 0``.
    """
    v = np.asarray(v, dtype=float)
    floor = float(np.min(v)) if v_min is None else float(v_min)
    top = float(np.max(v))
    s_lo, s_hi = divergence.slope_at_one
    lo = floor + lam * s_lo
    hi = top + lam * s_hi
    if np.isfinite(divergence.domain_max):
        edge = floor + lam * divergence.domain_max
        if divergence.domain_open:
            edge -= 1e-12 * max(1.0, abs(edge))
        hi = min(hi, edge)
    hi = max(hi, lo)
    m = E.matrix
    d = m.shape[0]

    def objective(alpha):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            fs = divergence.conjugate((alpha[:, None] - v[None, :]) / lam)
            val = alpha - lam * np.einsum("ij,ij->i", m, fs)
        return np.where(np.isfinite(val), val, -np.inf)

    invphi = (np.sqrt(5.0) - 1.0) / 2.0
    a = np.full(d, lo)
    bnd = np.full(d, hi)
    x1 = bnd - invphi * (bnd - a)
    x2 = a + invphi * (bnd - a)
    f1, f2 = objective(x1), objective(x2)
    best_f = np.maximum.reduce([objective(a), objective(bnd), f1, f2])
    for _ in range(max_iter):
        if np.all(bnd - a <= xtol * (1.0 + np.abs(a))):
            break
        go_left = f1 >= f2  # keep [a, x2]
        a = np.where(go_left, a, x1)
        bnd = np.where(go_left, x2, bnd)
        new_x = np.where(go_left, bnd - invphi * (bnd - a), a + invphi * (bnd - a))
        new_f = objective(new_x)
        x1, x2, f1, f2 = (
            np.where(go_left, new_x, x2),
            np.where(go_left, x1, new_x),
            np.where(go_left, new_f, f2),
            np.where(go_left, f1, new_f),
        )
        best_f = np.maximum(best_f, new_f)
    return best_f
