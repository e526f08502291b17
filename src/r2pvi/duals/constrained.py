"""Duals of the constrained problem ``inf {E_mu V : D(mu || mu0) <= rho}``, one per factor.

These are the d-rectangular *uncertainty-ball* (d-DRMDP) counterparts of
:mod:`r2pvi.duals.regularized`, used by the baselines DRPVI (TV ball, Liu & Xu 2024) and
DRVI-L (KL ball, Ma et al. 2022). Every function takes an expectation operator ``E`` (d
factors over n points), the values ``v (n,)`` at those points and the radii ``rho`` (a
scalar or one per factor), and returns the d dual values ``w (d,)``. With a
:class:`~r2pvi.duals.RidgeExpectation` they are the baselines' estimators; with a
:class:`~r2pvi.duals.FactorExpectation` they are the exact robust expectations.

A radius ``rho_i = 0`` makes the ball ``{mu0_i}``: the result is then the plain expectation
``E_i(v)``, never a conservative approximation of it, projected onto the known range of the
values ``v_range`` when one is given (as :class:`~r2pvi.PEVI` projects its estimate): the limit
of the result as ``rho_i -> 0+``, so the result is continuous at ``rho_i = 0``.
"""

from __future__ import annotations

import numpy as np

from ._kl_ball import _KLProblem
from .operator import ExpectationOperator
from .piecewise import tv_ball_max

__all__ = ["tv_constrained", "kl_constrained", "chi2_constrained"]


def _radii(rho, d: int) -> np.ndarray:
    """``rho`` as a (d,) array of finite, non-negative radii."""
    r = np.asarray(rho, dtype=float)
    if r.ndim == 0:
        r = np.full(d, float(r))
    elif r.shape != (d,):
        raise ValueError(f"rho must be a scalar or have shape (d,) = ({d},), got {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r < 0):
        raise ValueError(f"rho must be finite and >= 0, got {rho!r}")
    return r


# ---------------------------------------------------------------------------------- TV ball


def tv_constrained(
    E: ExpectationOperator,
    v: np.ndarray,
    rho,
    v_min: float | None = None,
    method: str = "auto",
    *,
    v_range=None,
) -> np.ndarray:
    """TV ball: ``max_{alpha in [V_min, V_max]} E_i[V]_alpha - rho_i (alpha - min_s [V(s)]_alpha)``.

    The dual of ``inf {E_mu V : D_TV(mu || mu0_i) <= rho_i}`` with ``D_TV = 1/2 sum |mu - mu0|``
    (paper, remark after Prop. TV duality, from Shi et al. 2024; Liu & Xu 2024, eq. (4.4)).
    For ``alpha >= V_min`` the last term is ``rho_i (alpha - V_min)``.

    The objective is piecewise linear in ``alpha`` with breakpoints at the values, so its
    maximum is attained at a breakpoint (or at ``V_min`` when that lies below the values), and
    every breakpoint is accounted for exactly, with no Nelder-Mead: ``method="dense"``
    evaluates them all from the prefix sums of
    :meth:`~r2pvi.duals.ExpectationOperator.truncation_cumulants`; ``"blockwise"`` gives the
    same maximum by the branch and bound over blocks of sorted breakpoints shared with the
    chi^2 dual (:class:`~r2pvi.duals.blockscan.BlockScan`); ``"auto"`` takes blockwise from
    512 values on. The values are shifted by ``V_min`` first, so that ``rho_i alpha`` never
    cancels against ``rho_i V_min``: any finite radius is exact (``rho = 1e16`` included).

    Guarantees (also for ridge operators, whose weights may be negative): the ball contains
    ``mu0_i``, so the result never exceeds the plain estimate ``E_i(v)`` (clipped to
    ``v_range``), and it is at least ``V_min``. With ``m_i = clip(E_i(v), lo, hi)``
    (``v_range = (lo, hi)``, unbounded when None), the result for ``rho_i > 0`` is
    ``min(max(dual_i, max(V_min, lo)), m_i)``: non-increasing in ``rho_i`` and tending to
    ``m_i`` as ``rho_i -> 0+``; ``rho_i = 0`` gives exactly ``m_i`` (the non-robust
    estimate projected onto ``v_range``, :class:`~r2pvi.PEVI`'s). A radius ``rho_i >= 1``
    makes the ball hold every distribution, whatever ``mu0_i``: the result is then
    ``min(V_min, m_i)``, exactly (a ridge row's dual would give ``V_min E_i(1)``). A
    ``v_min`` below ``lo`` (a known state value under the range) lowers the results' lower
    end to it; ``m_i`` keeps ``v_range``.

    Parameters
    ----------
    E : ExpectationOperator
    v : ndarray (n,)
        Values at the operator's points.
    rho : float or ndarray (d,)
        Radii, >= 0.
    v_min : float, optional
        Minimum of V over the whole state space (mass can move to any state under TV); None
        takes ``min(v)``. A ``v_min`` above ``min(v)`` is clamped to ``min(v)`` (the points of
        ``v`` are states too).
    method : {"auto", "dense", "blockwise"}
    v_range : (float, float), optional
        Known range ``(lo, hi)`` of V (e.g. ``[0, (H - h - 1) r_max]`` when learning): every
        result lies in it.

    Returns
    -------
    ndarray (d,)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, tv_constrained
    >>> E = FactorExpectation(np.array([[0.5, 0.5, 0.0]]))
    >>> v = np.array([1.0, 3.0, 0.0])
    >>> tv_constrained(E, v, rho=0.25)   # move 1/4 of the mass from V=3 to V=0
    array([1.25])
    >>> tv_constrained(E, v, rho=0.0), tv_constrained(E, v, rho=1.0)
    (array([2.]), array([0.]))
    >>> tv_constrained(E, v, rho=1e16)   # a saturated ball: exactly min V
    array([0.])
    """
    v = np.asarray(v, dtype=float)
    rho = _radii(rho, E.n_dims)
    lo, hi = _value_range(v_range)
    if method not in ("auto", "dense", "blockwise"):
        raise ValueError(f"method must be 'auto', 'dense' or 'blockwise', got {method!r}")
    lowest = float(np.min(v))
    floor = lowest if v_min is None else min(float(v_min), lowest)
    y = v - floor  # >= 0, and exactly 0 at the lowest point when floor == min(v)
    if not np.any(rho > 0):
        return np.clip(E(v), lo, hi)  # rho = 0: the plain estimate, projected
    if method == "auto":
        method = "blockwise" if v.size >= 512 else "dense"
    with np.errstate(over="ignore", invalid="ignore"):  # rho alpha may overflow to inf
        if method == "dense":
            best = _tv_ball_cumulants(E, y, rho)
            plain, mass = E(v), E(np.ones_like(v))
        else:
            totals = {}
            best = tv_ball_max(E, y, rho, totals)
            # E_i(1) and E_i(v) from the scan's block sums; E_i(v) itself where rho_i = 0
            mass = totals["mass"]
            plain = E(v) if np.any(rho == 0) else totals["mean"] + floor * mass
    cap = np.clip(plain, lo, hi)
    # alpha = V_min: E_i[y]_0 - 0 = 0 (a breakpoint already when floor == min(v))
    np.maximum(best, 0.0, out=best)
    best += floor * mass
    # A radius >= 1 allows every distribution, whatever mu0: the least value, exactly (the
    # ridge dual there is V_min E_i(1), biased by the row sum).
    best = np.where(rho >= 1.0, floor, best)
    # the least value; a v_min given below the range's lower end is a known state value
    lower = floor if v_min is not None and floor < lo else max(floor, lo)
    out = np.minimum(np.maximum(best, lower), cap)
    return np.where(rho > 0, out, cap)  # rho_i = 0: the plain estimate, projected (the limit)


def _value_range(v_range) -> tuple[float, float]:
    """``(lo, hi)`` from ``v_range`` (None: unbounded)."""
    if v_range is None:
        return -np.inf, np.inf
    try:
        lo, hi = (float(x) for x in v_range)
    except (TypeError, ValueError):
        raise TypeError(f"v_range must be None or a pair (lo, hi) of numbers, got {v_range!r}"
                        ) from None
    if np.isnan(lo) or np.isnan(hi) or lo > hi:
        raise ValueError(f"v_range must be a pair (lo, hi) with lo <= hi, got {v_range!r}")
    return lo, hi


def _tv_ball_cumulants(E, v, rho):
    """Every breakpoint from full prefix sums: ``max_k A_k + (B_k - rho) alpha_k`` (reference)."""
    cum = E.truncation_cumulants(v)
    obj = np.subtract(cum.b, rho[:, None], out=cum.b)  # the cumulants' buffers are ours now
    obj *= cum.alphas
    obj += cum.a
    return obj.max(axis=1)


# ---------------------------------------------------------------------------------- KL ball


def kl_constrained(
    E: ExpectationOperator,
    v: np.ndarray,
    rho,
    *,
    v_range=None,
    v_max: float | None = None,
    centered: bool = False,
    normalized: bool = False,
    b_min: float | None = None,
    xtol: float = 1e-12,
    max_iter: int = 60,
) -> np.ndarray:
    """KL ball: ``sup_{b > 0} -b log E_i[exp(-V/b)] - b rho_i``.

    The dual of ``inf {E_mu V : D_KL(mu || mu0_i) <= rho_i}`` (Hu & Hong 2013; used by
    DRVI-L, Ma et al. 2022). The estimate of ``u_i(b) = E_i[exp(-V/b)]`` is floored at
    ``exp(-m_i/b)``, ``m_i`` the plain estimate ``E_i(v)`` (clipped to ``v_range``): by
    Jensen's inequality a distribution has ``u_i(b) >= exp(-E_i[V]/b)``, so the floor never
    binds in exact evaluation, and ``-b log u_i - b rho_i <= m_i - b rho_i`` at every ``b``
    for any operator. (Ma et al. floor at ``exp(-H/b)``; with ridge weights that floor lets
    the objective reach ``H`` wherever the estimate of ``u_i`` crosses it, see below.)

    With ``centered=True`` the estimate is Ma et al.'s for a ridge operator, whose estimate of
    ``u_i`` can leave (0, 1]: regress ``exp(-V/b) - 1`` (the ridge estimate shrinks towards 1,
    not 0), then clip, ``u_i = 1 + clip(E_i(exp(-V/b) - 1), exp(-m_i/b) - 1, 0)``. For an
    operator whose rows sum to 1 (exact evaluation) both forms are the same.

    With ``normalized=True`` (DRVI-L's default) a ridge operator's factor is estimated as the
    ridge regression estimates any expectation: ``s_i`` times the exact dual under the
    row-normalized weights ``M_i / s_i`` (``s_i = E_i(1)``, the sum of the factor's ridge
    weights, below 1 by the ``gamma`` shrinkage), the KL-ball analogue of
    :func:`~r2pvi.duals.kl_regularized`'s default form. Ma et al.'s centering puts the
    shrinkage's leftover weight ``1 - s_i`` at ``V = 0``: where ``e^{-V/b}`` is small (values
    far from 0, ``b`` small) that leftover swamps the estimate of ``u_i`` and the result can
    fall below every value of V, whatever K (docs/numerical-guarantees.md). The normalized
    form has no
    leftover, tends to ``E_i(v)`` as ``rho_i -> 0+`` like the centered one, and equals the
    other forms for distributions. A factor with ``s_i <= 0`` (no positive total weight,
    signed features) gets its plain estimate.

    **The limit b -> 0 on ridge operators.** ``E_i(exp(-V/b) - 1)`` tends to minus the
    ridge weight of the points with ``V > 0``, which exceeds 1 whenever the row's weights on
    the lowest values are negative (a factor with no mass at the lowest value, estimated
    from overlapping features): the estimate of ``u_i`` then crosses 0 at a small ``b``, and
    below the crossing the floor makes the objective ``m_i - b rho_i``, nearly the plain
    estimate, whatever ``rho_i``. It is not the minimum of ``v`` over the factor's support
    (that limit holds for non-negative rows only). ``b_min`` (Ma et al.'s lower bound
    ``underline beta`` on the dual variable) excludes that region: DRVI-L sets it from the
    data (:class:`~r2pvi.DRVIL`).

    The 1-D problem is solved in ``t = log b`` for all factors at once (a grid, a quintic
    Hermite start, a safeguarded Newton iteration to 1e-14 of the values; the moments from
    Chebyshev and Taylor series where they are accurate to 1e-17 per unit of weight: see
    :mod:`r2pvi.duals._kl_ball`), in the log domain, shifted by the smallest value each factor
    can see: finite and accurate for values from 0 to 1e6 and beyond and ``b`` from 1e-9
    (relative to the values) to ``2 (max V - min V) / rho``. The grid is scaled by the values,
    never by a bound such as ``H r_max``.

    Guarantees: with ``v_range = (lo, hi)`` (unbounded when None) and ``m_i = clip(E_i(v),
    lo, hi)``, the result lies in ``[min(lower_i, m_i), m_i]``, ``lower_i = lo`` for a
    ridge operator and the smallest value on the factor's support (at least ``lo``) for a
    distribution, for ``rho_i > 0``; it is non-increasing in ``rho_i`` and tends to ``m_i``
    as ``rho_i -> 0+``; ``rho_i = 0`` gives exactly ``m_i`` (the non-robust estimate
    projected onto ``v_range``, :class:`~r2pvi.PEVI`'s). For a
    distribution, a radius ``rho_i >= log(1 / mu0_i(S_min))`` (``S_min``: where V is
    smallest on the support) makes the ball hold the point mass there: the result is that
    minimum, exactly.

    Parameters
    ----------
    E : ExpectationOperator
    v : ndarray (n,)
        Values at the operator's points.
    rho : float or ndarray (d,)
        Radii, >= 0.
    v_range : (float, float), optional
        Known range ``(lo, hi)`` of V over the state space (e.g. ``[0, (H - h - 1) r_max]``
        when learning): every result lies in it.
    v_max : float, optional
        Shorthand for ``v_range=(-inf, v_max)``.
    centered : bool, default False
        Ma et al.'s centered regression of ``exp(-V/b) - 1`` with the clip to
        ``[exp(-m_i/b) - 1, 0]`` (for ridge operators).
    normalized : bool, default False
        ``s_i`` times the dual under the row-normalized weights (for ridge operators; see
        above). Not together with ``centered``.
    b_min : float, optional
        Lower end of the search over ``b`` (Ma et al.'s ``underline beta``, in the units of
        V); None searches ``b -> 0`` too.
    xtol, max_iter
        Tolerance on ``t = log b`` and the iteration cap of the Newton refinement.

    Returns
    -------
    ndarray (d,)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, kl_constrained
    >>> E = FactorExpectation(np.array([[0.5, 0.5], [0.9, 0.1]]))
    >>> v = np.array([0.0, 1.0])
    >>> kl_constrained(E, v, rho=0.0)          # plain expectation
    array([0.5, 0.1])
    >>> kl_constrained(E, v, rho=0.1).round(6)  # worst case within KL radius 0.1
    array([0.280205, 0.000926])
    >>> kl_constrained(E, v, rho=5.0)          # radius beyond log(1/mu0(argmin)): min V
    array([0., 0.])
    """
    v = np.asarray(v, dtype=float)
    d = E.n_dims
    rho = _radii(rho, d)
    if v_range is None and v_max is not None:
        v_range = (-np.inf, v_max)
    lo, hi = _value_range(v_range)
    dims = np.flatnonzero(rho > 0)
    if dims.size == 0:
        return np.clip(E(v), lo, hi)  # rho = 0: the plain estimate, projected
    if b_min is not None and not (np.isfinite(b_min) and b_min > 0):
        raise ValueError(f"b_min must be a positive number or None, got {b_min!r}")
    if centered and normalized:
        raise ValueError("kl_constrained: choose centered=True (Ma et al.'s centered "
                         "regression) or normalized=True (the row-normalized weights), not both")
    prob = _KLProblem(E, v, rho, dims, lo, centered, normalized)
    plain = prob.prepare(b_min)  # E(v), with the grid's columns
    cap = np.clip(plain, lo, hi)
    prob.set_cap(cap)
    best = prob.solve(b_min, xtol, max_iter)
    if prob.scaled:  # normalized ridge rows: s_i times the dual per unit of row mass
        best = np.where(prob.live, best * prob.norm, cap[dims])
    out = cap.copy()  # rho_i = 0: the plain estimate, projected (the limit rho_i -> 0+)
    # Jensen's floor keeps every objective value <= cap - b rho; the min only absorbs rounding.
    # The lower end: every expectation of V is at least the least value (for a distribution,
    # the minimum on its support, which a saturated ball attains exactly).
    out[dims] = np.minimum(np.maximum(best, prob.lower), cap[dims])
    if prob.saturated is not None:  # the point mass at the minimum is in the ball: exactly it
        out[dims] = np.where(prob.saturated, np.minimum(prob.lower, cap[dims]), out[dims])
    return out


# ---------------------------------------------------------------------------------- chi^2 ball


def chi2_constrained(E: ExpectationOperator, v: np.ndarray, rho) -> np.ndarray:
    """chi^2 ball: ``sup_eta eta - sqrt(1 + rho_i) sqrt(E_i[(eta - V)_+^2])``.

    The dual of ``inf {E_mu V : chi2(mu || mu0_i) <= rho_i}`` with the paper's
    ``f(t) = (t - 1)^2``, i.e. ``chi2(mu || mu0) = sum_s (mu(s) - mu0(s))^2 / mu0(s)``: the
    ball of the robustly admissible set (Thm. instance-dependent upper bounds); Duchi &
    Namkoong (2021), Cressie-Read k = 2. Derivation: with ``L = mu / mu0``, minimize
    ``E0[L V]`` over ``L >= 0``, ``E0[L] = 1``, ``E0[L^2] <= 1 + rho``; the Lagrangian's
    infimum over ``L`` is ``eta - b (1 + rho) - E0[(eta - V)_+^2] / (4 b)`` and the best
    ``b > 0`` gives the formula. It equals Shi et al.'s (2023)
    ``max_alpha E0[V]_alpha - sqrt(rho Var0([V]_alpha))``. Mass stays on the support of
    ``mu0`` (the divergence is infinite elsewhere).

    The objective is concave in ``eta``. Between consecutive sorted values it is
    ``eta - c sqrt(m0 eta^2 - 2 m1 eta + m2)`` with prefix sums ``m0, m1, m2`` of the weights,
    weighted values and weighted squares (``c^2 = 1 + rho``), whose stationary point is
    ``eta* = (m1 + sqrt((m0 m2 - m1^2) / (c^2 m0 - 1))) / m0`` when ``c^2 m0 > 1`` (else the
    piece increases). The best of the pieces' stationary points, each clipped to its piece,
    is the exact maximum: one sort and O(n d) work. The values are shifted by each factor's
    smallest value on its support, so that the prefix sums do not cancel.

    Needs an operator whose rows are non-negative (``E.nonnegative``, e.g.
    :class:`~r2pvi.duals.FactorExpectation`); a row of total weight ``m != 1`` is treated
    as ``m`` times the distribution ``row / m``. ``rho_i = 0`` returns ``E_i(v)``; a radius
    ``rho_i >= 1 / mu0_i(s) - 1``, ``s`` a minimizer of V on the support, gives that minimum.

    Parameters
    ----------
    E : ExpectationOperator
        Non-negative operator; its rows are the nominal distributions ``mu0_i``.
    v : ndarray (n,)
        Values at the operator's points.
    rho : float or ndarray (d,)
        Radii, >= 0.

    Returns
    -------
    ndarray (d,)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, chi2_constrained
    >>> E = FactorExpectation(np.array([[0.5, 0.5, 0.0], [0.25, 0.25, 0.5]]))
    >>> v = np.array([0.0, 2.0, 1.0])
    >>> chi2_constrained(E, v, rho=0.0)             # plain expectation
    array([1., 1.])
    >>> chi2_constrained(E, v, rho=0.5).round(6)    # E V - sqrt(rho Var V): mu stays >= 0
    array([0.292893, 0.5     ])
    >>> chi2_constrained(E, v, rho=3.0)             # delta_{s0} is in both balls: min V
    array([0., 0.])
    """
    v = np.asarray(v, dtype=float)
    rho = _radii(rho, E.n_dims)
    plain = E(v)
    dims = np.flatnonzero(rho > 0)
    if dims.size == 0:
        return plain
    if not E.nonnegative:
        raise ValueError(
            "chi2_constrained needs an operator whose rows are distributions (E.nonnegative, "
            f"e.g. FactorExpectation), got {type(E).__name__}"
        )
    rows = np.asarray(E.rows(dims), dtype=float)  # (m, n)
    mass = rows.sum(axis=1)
    out = plain.copy()
    keep = mass > 0  # an empty row has no ball: E_i(v) = 0
    if not keep.any():
        return out
    dims, rows, mass = dims[keep], rows[keep], mass[keep]
    order = np.argsort(v, kind="stable")
    p = rows[:, order] / mass[:, None]  # the nominal distributions, values sorted
    base = np.where(p > 0, v[order], np.inf).min(axis=1)  # smallest value on each support
    y = v[order][None, :] - base[:, None]  # >= 0 on the support
    py = p * y
    m0, m1, m2 = np.cumsum(p, axis=1), np.cumsum(py, axis=1), np.cumsum(py * y, axis=1)
    c2 = (1.0 + rho[dims])[:, None]
    hi = np.concatenate([y[:, 1:], np.full((y.shape[0], 1), np.inf)], axis=1)
    steep = c2 * m0 > 1.0  # pieces with an interior maximum (the last piece always is)
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.maximum(m0 * m2 - m1 * m1, 0.0)
        eta = (m1 + np.sqrt(spread / (c2 * m0 - 1.0))) / m0
    eta = np.clip(np.where(steep, eta, y), y, hi)
    q = np.maximum(m0 * eta * eta - 2.0 * m1 * eta + m2, 0.0)
    best = base + np.where(steep, eta - np.sqrt(c2 * q), -np.inf).max(axis=1)
    mean = plain[dims] / mass
    out[dims] = mass * np.clip(best, base, np.maximum(mean, base))  # round-off: [min V, E V]
    return out
