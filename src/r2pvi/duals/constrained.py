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

import math

import numpy as np

from ._scratch import buffer
from .operator import ExpectationOperator, FactorExpectation, RidgeExpectation
from .piecewise import tv_ball_max

__all__ = ["tv_constrained", "kl_constrained"]


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
    chi^2 dual (:class:`~r2pvi.duals.piecewise.BlockScan`); ``"auto"`` takes blockwise from
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


def _factorization(E):
    """``(psi (n, p), R (d, p))`` with ``M = R psi^T`` for the operators whose structure is
    known (ridge: ``R = Lambda^{-1}``, ``psi = W Phi``; factors: ``R = I``, ``psi = mu^T``)."""
    if isinstance(E, RidgeExpectation) and E.primal_dense:  # dual form / sparse: E.matrix
        psi = E.phi if E.weights is None else E.phi * E.weights[:, None]
        linv = E.chol_inverse
        return psi, linv.T @ linv
    if isinstance(E, FactorExpectation):
        return E.mu.T, np.eye(E.n_dims)
    return None


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
    far from 0, ``b`` small) that leftover swamps the estimate of ``u_i`` and the result falls
    below every value of V (measured: 0.012-0.024 below the exact ball value, below ``min V``,
    on a 6-state linear MDP with ``gamma = 1``, whatever K). The normalized form has no
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

    The 1-D problem is solved in ``t = log b`` for all factors at once: the objective, its
    first and second derivatives on a log-spaced grid of ``b`` (one operator call for all
    factors) give each factor a bracket around its best grid point and, as a first guess,
    the maximizer of the quintic through the bracket's ends; a safeguarded Newton iteration
    (bisection when a step leaves the bracket) refines it until its predicted gain is below
    1e-14 of the values; the best value seen is returned. For ridge operators (``y = V -
    min V``), the moments ``E_i[T_k(2 y / max y - 1)]`` of 24 Chebyshev polynomials, read in
    the grid's operator call, give ``E_i[y^j exp(-y/b)]``, ``j = 0, 1, 2``, for every ``b``
    in ``[max y / 6, max |V|)`` (interpolation at the Chebyshev points: truncation below
    1e-17, rounding ~3e-15, per unit of weight): there the grid gets points 0.1 apart in
    ``log b`` and the Newton steps need no pass over the points. For smaller ``b`` (and for
    exact distributions, whose evaluation stays accurate to rounding relative to ``u_i``) a
    few shared nodes near the guesses keep the moments ``E_i[(y/b0)^k / k! exp(-y/b0)]`` (one
    operator call), from which a Taylor series in ``b0/b - 1`` gives any factor's objective
    within ``|log(b/b0)| <= 0.15`` to 1e-17 per unit of weight; above the values' scale (or
    where factors do not share their least value) grid points and Newton steps are evaluated
    directly. Everything is computed in the log domain,
    shifted by the smallest value each factor can see, with ``expm1`` for large ``b``: finite
    and accurate for values from 0 to 1e6 and beyond and ``b`` from 1e-9 (relative to the
    values) to ``2 (max V - min V) / rho``. The grid is scaled by the values, never by a
    bound such as ``H r_max``.

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
    prob.prepare(b_min)  # the grid's columns, read with E(v) where the operator streams
    plain = E(v)
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


class _KLProblem:
    """The KL-ball dual of the factors ``dims``: evaluation in log b on a grid and per factor."""

    def __init__(self, E, v, rho, dims, lo, centered, normalized=False):
        self.E, self.v, self.dims = E, v, dims
        self.rho = rho[dims]
        self.centered = bool(centered)
        # normalized ridge rows: the moments per unit of row mass, the result times s_i
        self.scaled = bool(normalized) and not E.nonnegative
        self.live = None
        self.scale = float(np.max(np.abs(v))) or 1.0
        lowest = float(np.min(v))
        # Smallest value each factor can see: the shift of the log-domain computation and,
        # for non-negative operators, the limit of the objective as b -> 0.
        if E.nonnegative:
            rows = E.rows(dims)
            self.shift = np.where(rows > 0, v, np.inf).min(axis=1)
            self.rows = rows
        else:
            self.shift = np.full(dims.size, lowest)
            self.rows = None
        self.shared_shift = bool(np.all(self.shift == self.shift[0]))
        self._w3 = None
        self._series = None  # Taylor moments at the local nodes (see _series_grid)
        # Chebyshev moments E_i[T_k(2 y / y_max - 1)] (see _cheb_basis): they serve every b in
        # [y_max / _CHEB_X, scale) without a pass over the points; b_cheb = inf: none
        self._cheb = None
        self._b_cheb = np.inf
        if self.shared_shift:
            self._y_shared = v - self.shift[0]
            self._y_negative = bool(np.any(self._y_shared < 0))
            y_max = float(np.max(self._y_shared))
            # (not for exact distributions: see _CHEB_X)
            if not self._y_negative and y_max > 0.0 and not E.nonnegative:
                self._y_max, self._b_cheb = y_max, y_max / _CHEB_X
                self._cheb_y = 0.5 * y_max * (_CHEB_S + 1.0)  # the interpolation points
        # Distributions (non-negative rows): normalize by the row sums, exact up to rounding,
        # so that u -> 1 as b -> inf exactly. Otherwise u_i = E_i[exp(-V/b)] + c_i with
        # c_i = 1 - E_i(1) for the centered estimate (E_i[exp(-V/b) - 1] + 1) and 0 if not;
        # then E(1) comes with the first grid (one pass over the points less).
        self.c = self.base = None
        if E.nonnegative:
            self._set_row_sums(E(np.ones_like(v))[dims])
        else:  # (scaled: the cap is divided by the row sums when they come)
            self.norm = np.ones(dims.size)
        self.cap = None  # set_cap
        self._coarse = None  # prepare
        if E.nonnegative:
            self.lower = np.maximum(self.shift, lo)
            # rho_i >= log(1 / mu0_i(argmin)): saturated (rounding could put a grid value an
            # ulp above the minimum otherwise)
            at_min = np.where(rows > 0, v, np.inf) == self.shift[:, None]
            p_min = np.where(at_min, rows, 0.0).sum(axis=1) / self.norm
            with np.errstate(divide="ignore"):
                self.saturated = self.rho >= -np.log(p_min)
        else:
            self.lower = np.full(dims.size, lo)
            self.saturated = None
        spread = max(float(np.max(v)) - min(0.0, lowest), 1e-12 * self.scale)
        with np.errstate(divide="ignore", over="ignore"):
            self.b_hi = np.minimum(2.0 * spread / self.rho, _B_CAP * self.scale)

    def set_cap(self, cap):
        """Jensen's floor of log u: ``-m_i / b``, ``m_i`` the plain estimate (clipped to the
        value range; per unit of row mass)."""
        self.cap = cap[self.dims] / self.norm

    def prepare(self, b_min):
        """The grid of log b and its transformed values (:meth:`_grid_fill`), registered with
        an operator that streams its points (``include``), so that the plain estimate's pass
        reads them too."""
        lo_b = b_min if b_min is not None else _B_FLOOR * self.scale
        hi_b = max(float(self.b_hi.max()), 4.0 * lo_b)
        tgrid = _log_grid(lo_b, hi_b, self.scale)
        state = self._grid_fill(np.exp(tgrid))
        include = getattr(self.E, "include", None)
        if state[0] is not None and include is not None:
            include(state[0])
        self._coarse = (tgrid, state)

    def _set_row_sums(self, row_sums):
        """``norm``, ``c`` and ``base`` from the row sums ``E_i(1)`` (see ``__init__``)."""
        m = self.dims.size
        nonneg = self.E.nonnegative
        if nonneg:
            self.norm = row_sums
        elif self.scaled:
            # no positive total weight: nothing to normalize (the plain estimate, see
            # kl_constrained); 1 keeps the arithmetic finite
            self.live = row_sums > 0.0
            self.norm = np.where(self.live, row_sums, 1.0)
            if self.cap is not None:  # set before the first grid brought E(1)
                self.cap = self.cap / self.norm
            nonneg = True  # per unit of row mass: u = E[exp(-V/b)] / s_i, as for distributions
        self.c = 1.0 - row_sums if self.centered and not nonneg else np.zeros(m)
        self.base = np.ones(m) if (nonneg or self.centered) else row_sums

    # ------------------------------------------------------------------ solver
    def solve(self, b_min, xtol, max_iter):
        if self._coarse is None:
            self.prepare(b_min)
        tgrid, state = self._coarse
        g, dg, d2g = self._grid_eval(np.exp(tgrid), state)
        if self._cheb is not None:
            tgrid, g, dg, d2g = self._cheb_refine_grid(tgrid, g, dg, d2g)
        n_grid = tgrid.size
        k = np.argmax(g, axis=1)
        r = np.arange(k.size)
        best = g[r, k]
        t, f1, f2 = tgrid[k], dg[r, k], d2g[r, k]
        k_lo = np.where(f1 > 0, k, np.maximum(k - 1, 0))  # bracket around the best
        k_hi = np.where(f1 > 0, np.minimum(k + 1, n_grid - 1), k)
        lo, hi = tgrid[k_lo], tgrid[k_hi]
        # First step: the maximizer of the quintic through the bracket's ends (values and two
        # derivatives, known from the grid), a far better start than Newton from one end.
        first = _hermite_argmax(lo, hi, g[r, k_lo], dg[r, k_lo], d2g[r, k_lo], g[r, k_hi],
                                dg[r, k_hi], d2g[r, k_hi])
        ftol = _FTOL * self.scale
        series = np.zeros(first.size, dtype=bool)
        if self._series_possible():
            # Factors starting in the shifted regime (b < scale): in the Chebyshev range,
            # evaluated from the grid's Chebyshev moments; below it, Taylor moments at a few
            # shared nodes covering their first steps, every Newton evaluation near a node
            # then a short series (no pass over the points either way). Factors with nothing
            # to refine (an empty bracket at an end of the grid, or a grid point that is
            # already optimal) need no nodes.
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                done = ~(hi - lo > xtol * (1.0 + np.abs(t))) | (
                    (f2 < 0) & (0.5 * f1 * f1 / np.abs(f2) <= ftol))
            start = np.where(np.isnan(first), 0.5 * (lo + hi), first)
            series = start < np.log(self.scale)
            self._t_range = (float(tgrid[0]), float(tgrid[-1]))
            # (the Chebyshev moments, when the grid brought them, serve b >= b_cheb)
            below = start < np.log(self._b_cheb) if self._cheb is not None else series
            self._series_cover(start[series & below & ~done], best)
        if not series.all():  # the others: a local grid of exact evaluations
            local = self._refine_locally(np.where(series, np.nan, first), lo, hi, best,
                                         tgrid[0], tgrid[-1])
            first = np.where(series, first, local)
        for it in range(max_iter):
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                newton = t - f1 / f2
                gain = 0.5 * f1 * f1 / np.abs(f2)
            go = (hi - lo > xtol * (1.0 + np.abs(t))) & ~((f2 < 0) & (gain <= ftol))
            if not go.any():
                break
            ok = (f2 < 0) & (newton > lo) & (newton < hi)
            step = np.where(ok, newton, 0.5 * (lo + hi))
            if it == 0:
                step = np.where(np.isnan(first), step, first)
            idx = np.flatnonzero(go)
            gi, d1i, d2i = self.per_factor(idx, np.exp(step[idx]))
            t[idx], f1[idx], f2[idx] = step[idx], d1i, d2i
            best[idx] = np.maximum(best[idx], gi)
            up = d1i > 0
            lo[idx] = np.where(up, step[idx], lo[idx])
            hi[idx] = np.where(up, hi[idx], step[idx])
        if b_min is None and self.E.nonnegative:
            np.maximum(best, np.minimum(self.shift, self.cap), out=best)  # b -> 0
        return best

    def _refine_locally(self, first, lo, hi, best, t_min, t_max):
        """Sharper starting points from a second, local grid shared by all factors.

        The quintic estimates ``first`` of the factors' maximizers (log b) usually cluster;
        a few shared evaluations spaced ``_LOCAL_STEP`` apart around them (n exponentials
        each, against n per factor and Newton step) give each factor a quintic on an interval
        ~8x narrower, whose maximizer is typically accurate enough that one Newton
        evaluation confirms it. Skipped when the estimates spread too far. The nodes stay in
        the searched range ``[t_min, t_max]`` (``b >= b_min``); ``best`` takes the local
        evaluations too (exact values of the objective).
        """
        valid = np.isfinite(first)
        if not valid.any():
            return first
        t_lo = max(float(first[valid].min()) - 0.5 * _LOCAL_STEP, float(t_min))
        t_hi = min(float(first[valid].max()) + 0.5 * _LOCAL_STEP, float(t_max))
        if not t_hi > t_lo:
            return first
        count = int(np.ceil((t_hi - t_lo) / _LOCAL_STEP)) + 1
        if count > _LOCAL_MAX:
            return first
        nodes = np.linspace(t_lo, t_hi, count)
        g, dg, d2g = self.on_grid(np.exp(nodes))
        np.maximum(best, g.max(axis=1), out=best)
        j = np.clip(np.searchsorted(nodes, np.where(valid, first, t_lo)) - 1, 0, count - 2)
        r = np.arange(first.size)
        local = _hermite_argmax(nodes[j], nodes[j + 1], g[r, j], dg[r, j], d2g[r, j],
                                g[r, j + 1], dg[r, j + 1], d2g[r, j + 1])
        use = valid & (local > lo) & (local < hi)
        return np.where(use, local, first)

    # ------------------------------------------------------------------ moments
    def on_grid(self, bs):
        """Objective and its t-derivatives at every grid ``b`` for every factor: (m, J) each.

        The transformed values of all grid points go to the operator in one call (one pass
        over the points' features), except for factors with different shifts (explicit rows).
        """
        return self._grid_eval(bs, self._grid_fill(bs))

    def _grid_fill(self, bs):
        """The transformed values of the grid points as the operator's columns ``(n, 3 J)``
        (plus the Chebyshev basis :meth:`_cheb_basis` while it is unknown and some ``b`` lies
        in its range, plus ``1`` for ``E(1)`` while the row sums are unknown), contiguous rows
        for the element-wise passes; None for the columns when there are none (every ``b``
        in the Chebyshev range, the basis known) or factors need explicit rows."""
        plain = bs >= self.scale
        cheb = ~plain & (bs >= self._b_cheb)  # from the Chebyshev moments, no column
        if not self._series_possible():
            cheb[:] = False
        n = self.v.size
        shifted_rows = (~plain & ~cheb).any() and not self.shared_shift
        sel = plain if shifted_rows else ~cheb
        j_all = int(sel.sum())
        n_basis = _CHEB_TERMS if cheb.any() and self._cheb is None else 0
        ones = self.c is None  # E(1) in the same call
        if not (j_all or n_basis or ones):
            return None, plain, cheb, 0, 0, False
        buf = buffer("klball.grid", (3 * j_all + n_basis + ones, n))
        if ones:
            buf[-1] = 1.0
        if n_basis:
            self._cheb_basis(buf[3 * j_all:3 * j_all + n_basis])
        y = buf[:3 * j_all].reshape(3, j_all, n)
        jp = int(plain.sum())
        js = j_all - jp
        if js:  # shifted grid points the Chebyshev moments do not serve: the first columns
            b = bs[sel & ~plain]
            ys = self._y_shared
            np.multiply.outer(-1.0 / b, np.maximum(ys, 0.0) if self._y_negative else ys,
                              out=y[0, :js])
            np.exp(y[0, :js], out=y[0, :js])
            np.multiply(y[0, :js], ys, out=y[1, :js])
            np.multiply(y[1, :js], ys, out=y[2, :js])
        if jp:
            b = bs[plain]
            e1 = np.multiply.outer(-1.0 / b, self.v, out=y[0, js:])
            ex = np.exp(e1, out=y[1, js:])
            # exp(-V/b) - 1: ex - 1 carries ex's rounding (<= 2^-53), which moves
            # G = -b log u by about b 2^-53 sum |M_i| (< 1e-14 of the values for
            # b <= 64 max |V|); expm1, exact to the last digit, for larger b.
            big = int(np.searchsorted(b, _EXPM1_FROM * self.scale, side="right"))
            np.expm1(e1[big:], out=e1[big:])
            np.subtract(ex[:big], 1.0, out=e1[:big])
            ex *= self.v
            np.multiply(ex, self.v, out=y[2, js:])
        return buf.T, plain, cheb, j_all, n_basis, ones

    def _grid_eval(self, bs, state):
        """:meth:`on_grid` from the columns of :meth:`_grid_fill` (one operator call)."""
        cols, plain, cheb, j_all, n_basis, ones = state
        out = [np.empty((self.dims.size, bs.size)) for _ in range(3)]
        if cols is not None:
            mom = self.E(cols)[self.dims]
            if ones:
                self._set_row_sums(mom[:, -1].copy())
                mom = mom[:, :-1]
            mom /= self.norm[:, None]
            if n_basis:
                self._cheb = mom[:, 3 * j_all:].copy()
            mom = mom[:, :3 * j_all].reshape(self.dims.size, 3, j_all)
            jp = int(plain.sum())
            js = j_all - jp
            if jp:
                res = self._plain(mom[:, 0, js:], mom[:, 1, js:], mom[:, 2, js:],
                                  bs[None, plain], self.base[:, None], self.rho[:, None],
                                  self.cap[:, None])
                for o, val in zip(out, res, strict=True):
                    o[:, plain] = val
            if js:
                s_idx = np.flatnonzero(~plain & ~cheb)
                res = self._objective(mom[:, 0, :js], mom[:, 1, :js], mom[:, 2, :js],
                                      bs[s_idx])
                for o, val in zip(out, res, strict=True):
                    o[:, s_idx] = val
        if cheb.any():
            coef = self._cheb_coefficients(bs[cheb])  # (3, J, terms)
            x0, x1, x2 = (self._cheb @ coef[k].T for k in range(3))
            res = self._objective(x0, x1, x2, bs[cheb])
            for o, val in zip(out, res, strict=True):
                o[:, cheb] = val
        if (~plain).any() and not self.shared_shift:
            # non-negative operator whose factors see different minima: explicit rows
            # (self.rows is set for non-negative operators)
            b = bs[~plain]
            y = np.maximum(self.v[None, :] - self.shift[:, None], 0.0)  # (m, n)
            z = np.exp(-y[:, None, :] / b[None, :, None])  # (m, J, n)
            x0 = np.einsum("in,ijn->ij", self.rows, z)
            z *= y[:, None, :]
            x1 = np.einsum("in,ijn->ij", self.rows, z)
            z *= y[:, None, :]
            x2 = np.einsum("in,ijn->ij", self.rows, z)
            x0, x1, x2 = (x / self.norm[:, None] for x in (x0, x1, x2))
            res = self._objective(x0, x1, x2, b)
            for o, val in zip(out, res, strict=True):
                o[:, ~plain] = val
        return out

    def per_factor(self, idx, b):
        """Objective and t-derivatives of factors ``idx`` (positions in ``dims``), each at its
        own ``b``, without a pass over the points where possible: from the Chebyshev moments
        for ``b`` in their range (:meth:`_cheb_at`), else in the shifted regime (``b <
        scale``) from the Taylor moments of a node within ``_SERIES_RADIUS`` once nodes exist
        (:meth:`_series_at`; nodes are added where none is), else exactly
        (:meth:`_per_factor_exact`)."""
        route = np.zeros(idx.size, dtype=np.int8)  # 0 exact, 1 Taylor node, 2 Chebyshev
        j = None
        if self._cheb is not None:
            route[(b < self.scale) & (b >= self._b_cheb)] = 2
        if self._series is not None:
            t = np.log(b)
            eligible = (route == 0) & (t < np.log(self.scale))
            if eligible.any():
                j, near = self._nearest_node(t)
                missing = eligible & ~near
                if missing.any():
                    self._series_cover(t[missing], None)
                    j, near = self._nearest_node(t)
                route[eligible & near] = 1
        out = tuple(np.empty(idx.size) for _ in range(3))
        for kind in (0, 1, 2):
            sel = route == kind
            if not sel.any():
                continue
            if kind == 2:
                res = self._cheb_at(idx[sel], b[sel])
            elif kind == 1:
                res = self._series_at(idx[sel], b[sel], j[sel])
            else:
                res = self._per_factor_exact(idx[sel], b[sel])
            if sel.all():
                return res
            for o, r in zip(out, res, strict=True):
                o[sel] = r
        return out

    def _per_factor_exact(self, idx, b):
        """:meth:`per_factor` by row-wise products of the explicit weights with the
        transformed values (n exponentials per factor)."""
        g, d1, d2 = (np.empty(idx.size) for _ in range(3))
        plain = b >= self.scale
        for sel, is_plain in ((np.flatnonzero(plain), True), (np.flatnonzero(~plain), False)):
            if sel.size == 0:
                continue
            rows, bb = idx[sel], b[sel]
            m = sel.size
            n = self.v.size
            z = buffer("klball.z", (3, m, n))
            if is_plain:
                np.multiply.outer(-1.0 / bb, self.v, out=z[0])
                np.exp(z[0], out=z[1])
                np.expm1(z[0], out=z[0])
                np.multiply(z[1], self.v, out=z[1])
                np.multiply(z[1], self.v, out=z[2])
            elif self.shared_shift:
                # One exp per (factor, point); the powers of y sit in the weight rows
                # (:meth:`_moment_rows`), so the three moments are one batched product.
                y = self._y_shared
                e = np.multiply.outer(-1.0 / bb, y, out=z[0])
                if self._y_negative:  # points outside a factor's support: weight 0
                    np.minimum(e, 0.0, out=e)
                np.exp(e, out=e)
                w3 = self._moment_rows(rows)
                mom = np.matmul(w3, e[:, :, None])[:, :, 0].T / self.norm[rows]
            else:
                y = self.v[None, :] - self.shift[rows, None]
                np.multiply(y, (-1.0 / bb)[:, None], out=z[0])
                np.minimum(z[0], 0.0, out=z[0])  # points outside a factor's support: weight 0
                np.exp(z[0], out=z[0])
                np.multiply(z[0], y, out=z[1])
                np.multiply(z[1], y, out=z[2])
            if is_plain or not self.shared_shift:
                mom = self._diagonal(z.reshape(3 * m, n), rows) / self.norm[rows]
            if is_plain:
                res = self._plain(mom[0], mom[1], mom[2], bb, self.base[rows], self.rho[rows],
                                  self.cap[rows])
            else:
                res = self._objective(mom[0], mom[1], mom[2], bb, rows)
            g[sel], d1[sel], d2[sel] = res
        return g, d1, d2

    def _moment_rows(self, rows):
        """``(m, 3, n)``: the weight rows of factors ``rows`` (positions in ``dims``) times
        ``1, y, y^2`` (``y = V - shift``, shared shift), formed once per call: then the
        moments ``E_i[y^k exp(-y/b_i)]`` of a Newton step are one batched matrix-vector
        product."""
        if self._w3 is None:
            w = self._weight_rows()
            y = self._y_shared
            w3 = buffer("klball.w3", (w.shape[0], 3, w.shape[1]))
            w3[:, 0] = w
            np.multiply(w, y, out=w3[:, 1])
            np.multiply(w3[:, 1], y, out=w3[:, 2])
            self._w3 = w3
        if rows.size == self._w3.shape[0]:
            return self._w3
        return np.take(self._w3, rows, axis=0,
                       out=buffer("klball.w3rows", (rows.size,) + self._w3.shape[1:]))

    def _weight_rows(self):
        """The operator's weight rows of the factors ``dims`` (computed once per call)."""
        if self.rows is None:
            factors = _factorization(self.E)
            if factors is None:
                full = self.E.matrix
                self.rows = full if self.dims.size == full.shape[0] else full[self.dims]
            else:  # M = R psi^T by one GEMM into a reused buffer
                psi, r = factors
                out = buffer("klball.rows", (self.dims.size, psi.shape[0]))
                self.rows = np.matmul(r[self.dims], psi.T, out=out)
        return self.rows

    def _diagonal(self, zs, rows):
        """``E_{dims[rows[j]]}(zs[k m + j])``, k = 0, 1, 2, by the explicit weight rows: (3, m)."""
        m = rows.size
        self._weight_rows()
        w = self.rows if m == self.rows.shape[0] else self.rows[rows]
        return np.stack([np.einsum("jn,jn->j", w, zs[k * m:(k + 1) * m]) for k in range(3)])

    # ------------------------------------------------------------------ Chebyshev moments
    def _cheb_basis(self, out):
        """The Chebyshev polynomials ``T_k(s)``, ``s = 2 y / y_max - 1`` in [-1, 1], ``k = 0 ..
        _CHEB_TERMS - 1``, at every point, into the rows of ``out`` (by the recurrence
        ``T_k = 2 s T_{k-1} - T_{k-2}``; ``|T_k| <= 1``). Their moments ``E_i[T_k]``, one
        operator call with the grid, give ``E_i[y^j exp(-y/b)]`` for every ``b`` in
        ``[y_max / _CHEB_X, scale)`` (:meth:`_cheb_at`)."""
        out[0] = 1.0
        s = out[1]
        np.multiply(self._y_shared, 2.0 / self._y_max, out=s)
        s -= 1.0
        np.clip(s, -1.0, 1.0, out=s)
        two_s = np.multiply(s, 2.0, out=buffer("klball.two_s", s.shape))
        for k in range(2, out.shape[0]):
            np.multiply(out[k - 1], two_s, out=out[k])
            out[k] -= out[k - 2]

    def _cheb_refine_grid(self, tgrid, g, dg, d2g):
        """The grid with points ``_CHEB_STEP`` apart (in log b) added across the Chebyshev
        range, evaluated from the Chebyshev moments (no pass over the points): every factor's
        objective is seen there at 7.5x the coarse grid's density, so an interior maximum
        between two coarse points (the objective of a ridge factor need not be concave) is
        bracketed, and the first Newton point comes from a narrow bracket."""
        t_lo = max(math.log(self._b_cheb), float(tgrid[0]))
        t_hi = min(math.log(self.scale), float(tgrid[-1]))
        fine = np.arange(t_lo, t_hi, _CHEB_STEP)
        b = np.exp(fine)
        keep = (b >= self._b_cheb) & (b < self.scale)
        keep &= np.abs(fine[:, None] - tgrid[None, :]).min(axis=1) > 0.25 * _CHEB_STEP
        if not keep.any():
            return tgrid, g, dg, d2g
        fine = fine[keep]
        extra = self.on_grid(b[keep])  # Chebyshev points only: no operator call
        order = np.argsort(np.concatenate([tgrid, fine]), kind="stable")
        merged = (np.concatenate([x, y], axis=1)[:, order]
                  for x, y in zip((g, dg, d2g), extra, strict=True))
        return (np.concatenate([tgrid, fine])[order], *merged)

    def _cheb_coefficients(self, b):
        """``(3, P, _CHEB_TERMS)``: the Chebyshev coefficients of the interpolants of
        ``y^j exp(-y/b_p)``, ``j = 0, 1, 2``, on ``[0, y_max]`` (:func:`_cheb_terms`)."""
        y = self._cheb_y
        f = np.empty((3, b.size, y.size))
        np.multiply.outer(-1.0 / b, y, out=f[0])
        np.exp(f[0], out=f[0])
        np.multiply(f[0], y, out=f[1])
        np.multiply(f[1], y, out=f[2])
        return f @ _CHEB_MATRIX.T

    def _cheb_at(self, idx, b):
        """:meth:`per_factor` of factors ``idx`` at their ``b`` (in the Chebyshev range) from
        the Chebyshev moments: ``X_j = sum_k c_jk(b) E_i[T_k]``."""
        coef = self._cheb_coefficients(b)
        mom = self._cheb[idx]
        x0, x1, x2 = (np.einsum("pk,pk->p", coef[k], mom) for k in range(3))
        return self._objective(x0, x1, x2, b, idx)

    # ------------------------------------------------------------------ Taylor moments
    def _series_possible(self) -> bool:
        """Whether Taylor moments apply: one shift shared by all factors, ``y = V - shift >= 0``
        at every point (ridge operators; distributions with a common support minimum)."""
        return self.shared_shift and not self._y_negative

    def _nearest_node(self, t):
        """Index of the node nearest to each ``t`` and whether it is within the radius."""
        nodes = self._series[0]
        if nodes.size == 1:
            j = np.zeros(t.size, dtype=np.intp)
        else:
            j = np.clip(np.searchsorted(nodes, t), 1, nodes.size - 1)
            j = np.where(t - nodes[j - 1] <= nodes[j] - t, j - 1, j)
        return j, np.abs(t - nodes[j]) <= _SERIES_RADIUS

    def _series_cover(self, ts, best):
        """Add nodes (within the searched range of log b) so that every ``ts`` is within
        ``_SERIES_RADIUS`` of one: greedily, the least uncovered point and those up to two
        radii above it share a node at the middle of their range (the Newton steps that
        follow stay near these points). ``best`` (if given) takes the objective at the new
        nodes (exact values, as every evaluation)."""
        pts = np.sort(ts[np.isfinite(ts)])
        t_min, t_max = self._t_range
        new = []
        i = 0
        reach = 1.998 * _SERIES_RADIUS  # margin for the rounding of t - node
        while i < pts.size:
            last = int(np.searchsorted(pts, pts[i] + reach, side="right"))
            node = 0.5 * (float(pts[i]) + float(pts[last - 1]))
            new.append(min(max(node, t_min), t_max))
            i = last
        if not new:
            return
        g = self._series_grid(np.array(new))[0]
        if best is not None:
            np.maximum(best, g.max(axis=1), out=best)

    def _series_grid(self, nodes):
        """Objective and t-derivatives at new nodes (as :meth:`on_grid`), keeping the moments
        ``E_i[C_k]``, ``C_k = (y/b)^k / k! exp(-y/b)``, ``k = 0 .. _SERIES_ORDER + 2``, of
        every node ``b``: one exponential per point and node, the powers by products, one
        operator call for all columns. :meth:`_series_at` then evaluates any factor at any
        ``b'`` near a node without a pass over the points (:func:`_series_moments`)."""
        bs = np.exp(nodes)
        y = self._y_shared
        order = _series_order(float(np.max(y)) / float(bs.min()))
        n, ncol = self.v.size, order + 3
        cols = buffer("klball.series", (bs.size, ncol, n))
        k = np.arange(1, ncol)
        for j, b in enumerate(bs):
            c = cols[j]
            np.multiply(y, -1.0 / b, out=c[0])
            np.exp(c[0], out=c[0])
            np.multiply.outer(1.0 / (b * k), y, out=c[1:])  # y / (k b)
            for i in k:  # C_k = C_{k-1} y / (k b) (a loop of rows: accumulate is 6x slower)
                np.multiply(c[i], c[i - 1], out=c[i])
        full = np.zeros((self.dims.size, bs.size, _SERIES_ORDER + 3))  # higher terms: 0
        mom = self.E(cols.reshape(bs.size * ncol, n).T)[self.dims]
        mom /= self.norm[:, None]
        full[:, :, :ncol] = mom.reshape(self.dims.size, bs.size, ncol)
        mom = full
        if self._series is not None and self._series[0].size:
            old_nodes, old_bs, old_mom = self._series
            nodes = np.concatenate([old_nodes, nodes])
            order = np.argsort(nodes, kind="stable")
            self._series = (nodes[order], np.concatenate([old_bs, bs])[order],
                            np.concatenate([old_mom, mom], axis=1)[:, order])
        else:
            self._series = (nodes, bs, mom)
        x0, x1, x2 = mom[:, :, 0], mom[:, :, 1] * bs, 2.0 * mom[:, :, 2] * (bs * bs)
        return self._objective(x0, x1, x2, bs)

    def _series_at(self, idx, b, j):
        """:meth:`per_factor` of factors ``idx`` at their ``b`` from the moments of node
        ``j`` (per factor; ``|log b - log b_j| <= _SERIES_RADIUS``)."""
        _, bs, mom = self._series
        x0, x1, x2 = _series_moments(mom[idx, j], bs[j], b)
        return self._objective(x0, x1, x2, b, idx)

    # ------------------------------------------------------------------ objective
    def _objective(self, x0, x1, x2, b, idx=None):
        """:meth:`_shifted` from the moments of ``y``: of factors ``idx`` (positions in
        ``dims``) each at its own ``b``, or (``idx`` None) of every factor at every ``b``,
        ``(m, J)``."""
        if idx is None:
            return self._shifted(x0, x1, x2, self.shift[:, None], b[None, :], self.c[:, None],
                                 self.rho[:, None], self.cap[:, None])
        return self._shifted(x0, x1, x2, self.shift[idx], b, self.c[idx], self.rho[idx],
                             self.cap[idx])

    def _plain(self, e1, p1, p2, b, base, rho, cap):
        """From ``D = E[exp(-V/b) - 1]``, ``P1 = E[V exp(-V/b)]``, ``P2 = E[V^2 exp(-V/b)]``
        (accurate for large b): ``u = base + D`` with ``base = 1`` (centered, or normalized
        distributions) or ``E(1)``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            w = e1 + (base - 1.0)
            log_u = np.where(w > -1.0, np.log1p(np.maximum(w, -1.0)), -np.inf)
            u = 1.0 + w
            t1 = p1 / (b * u)
            b3g2 = -(p2 * u - p1 * p1) / (u * u)
        return self._finish(log_u, t1, b3g2, b, rho, cap)

    def _shifted(self, x0, x1, x2, m, b, c, rho, cap):
        """From the moments of ``y = V - m``: ``X_k = E[y^k exp(-y/b)]`` (accurate for small b):
        ``u = exp(-m/b) X_0 + c``."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
            pos = x0 > 0
            if pos.all() and (c > 0).all():  # the usual case, without the masks (same values)
                q = x1 / x0
                var = x2 / x0 - q * q
                log_p = -m / b + np.log(x0)
                log_u = np.logaddexp(log_p, np.log(c))
                frac = np.exp(log_p - log_u)
                mean = m + q
                t1 = frac * mean / b
                b3g2 = -frac * (var + (1.0 - frac) * mean * mean)
                return self._finish(log_u, t1, b3g2, b, rho, cap)
            log_x = np.log(np.where(pos, x0, 1.0))
            q = np.where(x0 != 0, x1 / x0, 0.0)  # tilted mean of y
            var = np.where(x0 != 0, x2 / x0, 0.0) - q * q  # tilted variance
            log_p = -m / b + log_x
            if not np.any(c):
                log_u = np.where(pos, log_p, -np.inf)
                frac = np.ones_like(log_u)
            else:
                both = pos & (c > 0)
                log_c = np.log(np.where(c > 0, c, 1.0))
                p = np.where(pos, np.exp(log_p), x0 * np.exp(-m / b))
                u = p + c
                log_u = np.where(both, np.logaddexp(log_p, log_c),
                                 np.where(u > 0, np.log(np.where(u > 0, u, 1.0)), -np.inf))
                frac = np.where(both, np.exp(log_p - log_u), np.where(u != 0, p / u, 0.0))
            mean = m + q
            t1 = frac * mean / b
            b3g2 = -frac * (var + (1.0 - frac) * mean * mean)
        return self._finish(log_u, t1, b3g2, b, rho, cap)

    def _finish(self, log_u, t1, b3g2, b, rho, cap):
        """Clip ``log u`` to ``[-m/b, 0 if centered]`` (``m = cap``, Jensen's floor) and return
        ``G, dG/dt, d2G/dt2`` of ``G(t) = -b (log u + rho)``, ``b = e^t``; ``t1 = b u'/u`` and
        ``b3g2 = b^3 g''(b)``."""
        log_lo = -cap / b  # (b broadcasts against log_u in every formula below)
        low = ~(log_u >= log_lo)  # NaN/-inf too
        if low.any():
            log_u = np.where(low, log_lo, log_u)
            t1 = np.where(low, -log_lo, t1)
            b3g2 = np.where(low, 0.0, b3g2)
        if self.centered:
            high = log_u > 0.0
            if high.any():
                log_u = np.where(high, 0.0, log_u)
                t1 = np.where(high, 0.0, t1)
                b3g2 = np.where(high, 0.0, b3g2)
        gp = -log_u - t1 - rho  # dg/db
        g = -b * (log_u + rho)
        d1 = b * gp
        d2 = d1 + b3g2 / b
        finite = np.isfinite(g)
        if not finite.all():
            bad = ~finite
            g, d1, d2 = np.where(bad, -np.inf, g), np.where(bad, 0.0, d1), np.where(bad, -1.0, d2)
        return g, d1, d2


def _quintic_coefficients(t0, t1, g0, d0, dd0, g1, d1, dd1):
    """``(c1, ..., c5)`` of the quintic ``p(s) = g0 + c1 s + ... + c5 s^5`` on ``s in [0, 1]``
    (``t = t0 + s (t1 - t0)``) with the given values, first and second derivatives in t at
    both ends (quintic Hermite interpolation)."""
    h = t1 - t0
    c1, c2 = h * d0, 0.5 * h * h * dd0
    a = g1 - (g0 + c1 + c2)
    b = h * d1 - (c1 + 2.0 * c2)
    c = h * h * dd1 - 2.0 * c2
    c3 = 10.0 * a - 4.0 * b + 0.5 * c
    return c1, c2, c3, -15.0 * a + 7.0 * b - c, 6.0 * a - 3.0 * b + 0.5 * c


def _hermite_argmax(t0, t1, g0, d0, dd0, g1, d1, dd1, iters: int = 12):
    """Per row, the maximizer in ``(t0, t1)`` of the quintic with the given values, first and
    second derivatives at both ends (NaN where the data are not finite, the interval is empty
    or no interior maximum is found): a starting point for the safeguarded Newton iteration,
    which alone decides the result."""
    h = t1 - t0
    with np.errstate(all="ignore"):
        c1, c2, c3, c4, c5 = _quintic_coefficients(t0, t1, g0, d0, dd0, g1, d1, dd1)
        # Newton on p'(s) = 0 from the best of _HERMITE_GRID (p(s) = g0 + c1 s + ... + c5 s^5),
        # kept in [0, 1]. From an end, Newton can stop at a stationary inflection (p(t) = t^3 -
        # t^5 from t = -0.25: p' -> 0 at 0 while the maximum is at 0.77) or miss the second of
        # two interior maxima; the grid puts it next to the largest (unless narrower than the
        # grid's spacing).
        g = _HERMITE_GRID
        on_grid = g0[:, None] + g * (c1[:, None] + g * (c2[:, None] + g * (
            c3[:, None] + g * (c4[:, None] + g * c5[:, None]))))
        j = np.argmax(on_grid, axis=1)
        grid_best = on_grid[np.arange(j.size), j]
        s = g[j]
        s_prev = np.full_like(s, np.nan)
        a2, a3, a4, a5 = 2.0 * c2, 3.0 * c3, 4.0 * c4, 5.0 * c5  # p'(s) = c1 + a2 s + ...
        b3, b4, b5 = 6.0 * c3, 12.0 * c4, 20.0 * c5  # p''(s) = a2 + b3 s + ...
        for it in range(iters):
            p1 = c1 + s * (a2 + s * (a3 + s * (a4 + s * a5)))
            p2 = a2 + s * (b3 + s * (b4 + s * b5))
            p2[~(p2 < 0)] = -np.inf  # Newton only where p is concave (no step elsewhere)
            s_new = np.minimum(np.maximum(s - p1 / p2, 0.0), 1.0)
            moved = np.abs(s_new - s) > 1e-13
            if not moved.any():
                s = s_new
                break
            # A row back where it was two steps ago cycles for good (the map is fixed): stop
            # iterating once every moving row cycles, each at the point the full count of
            # iterations would reach (the cycle's parity).
            if (s_new[moved] == s_prev[moved]).all():
                s = np.where(moved & ((iters - 1 - it) % 2 == 1), s, s_new)
                break
            s_prev, s = s, s_new
        p1 = c1 + s * (a2 + s * (a3 + s * (a4 + s * a5)))
        p0 = g0 + s * (c1 + s * (c2 + s * (c3 + s * (c4 + s * c5))))
        good = (h > 0) & (s > 0.0) & (s < 1.0) & np.isfinite(s) & np.isfinite(
            g0 + g1 + d0 + d1 + dd0 + dd1) & (np.abs(p1) <= 1e-6 * (np.abs(c1) + np.abs(h * d1)))
        # no worse than the best grid point (up to rounding in the polynomial's value)
        good &= p0 >= grid_best - 1e-12 * (np.abs(g0) + np.abs(c1) + np.abs(c2) + np.abs(c3)
                                             + np.abs(c4) + np.abs(c5))
    return np.where(good, t0 + h * s, np.nan)


_HERMITE_GRID = np.linspace(0.0, 1.0, 17)  # starting points of _hermite_argmax (s in [0, 1])


_EXPM1_FROM = 64.0  # on the grid, expm1 (not exp - 1) for b above this many max |V|
_LOCAL_STEP = 0.1  # spacing (in log b) of the local grid of _KLProblem._refine_locally
_LOCAL_MAX = 12  # at most this many local evaluations, else no local grid
_B_FLOOR = 1e-9  # smallest b searched (b_min=None), relative to the values
_B_CAP = 1e16  # largest b searched, relative to the values: rho below ~1e-30 acts as 0
_FTOL = 1e-14  # Newton stops when its predicted gain is below this, relative to the values


def _log_grid(lo_b, hi_b, scale):
    """Grid of ``t = log b``: step 0.75 from ``1e-3 scale`` up (where the maximizers of the
    learning problems lie), step 2.5 below (the objective is nearly linear in b there)."""
    t_lo, t_hi = np.log(lo_b), np.log(hi_b)
    t_mid = min(max(np.log(1e-3 * scale), t_lo), t_hi)
    coarse = np.linspace(t_lo, t_mid, int(np.ceil((t_mid - t_lo) / 2.5)) + 1)
    fine = np.linspace(t_mid, t_hi, int(np.ceil((t_hi - t_mid) / 0.75)) + 1)
    return np.concatenate([coarse[:-1], fine])


def _series_order(x_max: float) -> int:
    """The least order N <= _SERIES_ORDER whose truncation bound (see
    :func:`_series_moments`) is below ``_SERIES_TOL`` for ``|log(b/b0)| <= _SERIES_RADIUS``,
    given ``x = y/b0 <= x_max``: the lesser of ``(x_max q)^(N+1) / (N+1)!`` and
    ``(q/(1-q))^(N+1) / sqrt(2 pi (N+1))``, ``q = e^R - 1``; ``_SERIES_ORDER`` meets the second
    for any ``x``."""
    q = math.expm1(_SERIES_RADIUS)
    log_tol = math.log(_SERIES_TOL)
    for order in range(_SERIES_ORDER):
        k = order + 1
        if x_max * q == 0 or k * math.log(x_max * q) - math.lgamma(k + 1) <= log_tol:
            return order
    return _SERIES_ORDER


def _series_moments(mom, b0, b):
    """``X_k = E[y^k exp(-y/b)]``, k = 0, 1, 2, from the moments ``mom[:, k] = E[C_k]``,
    ``C_k = (y/b0)^k / k! exp(-y/b0)`` of a node ``b0`` (one row per factor):
    ``exp(-y/b) = exp(-y/b0) sum_k (-beta)^k (y/b0)^k / k!`` with ``beta = b0/b - 1``, so
    ``X_0 = sum_k (-beta)^k E[C_k]``, ``X_1 = b0 sum_k (k+1) (-beta)^k E[C_{k+1}]``,
    ``X_2 = b0^2 sum_k (k+1)(k+2) (-beta)^k E[C_{k+2}]``, ``k <= _SERIES_ORDER``.

    Truncation: per point of weight ``|w|`` and ``x = y/b0``, the remainder of ``X_0`` is at
    most ``|w| exp(-x (1 - |beta|)) (x |beta|)^(N+1) / (N+1)!`` (Lagrange's remainder), which
    is at most ``|w| (x_max |beta|)^(N+1) / (N+1)!`` for ``x <= x_max`` and at most
    ``|w| (|beta| / (1 - |beta|))^(N+1) / sqrt(2 pi (N+1))`` for any ``x`` (``z^n e^-z / n! <=
    1 / sqrt(2 pi n)``). :func:`_series_order` takes the least N with one of them below
    ``_SERIES_TOL = 1e-17`` for ``|log(b/b0)| <= _SERIES_RADIUS = 0.15`` (``|beta| <= e^0.15 -
    1``); N = 22 suffices for any x. Columns above a node's order are 0. ``X_1`` and ``X_2``
    carry the remainder times ``b0 x`` and ``b0^2 x^2``.
    """
    n = _SERIES_ORDER + 1
    beta = b0 / b - 1.0
    powers = np.empty((beta.size, n))
    powers[:, 0] = 1.0
    powers[:, 1:] = -beta[:, None]
    np.multiply.accumulate(powers, axis=1, out=powers)  # (-beta)^k, k = 0 .. N
    x0 = np.einsum("ik,ik->i", powers, mom[:, :n])
    x1 = b0 * np.einsum("ik,ik->i", powers * _K1, mom[:, 1:n + 1])
    x2 = (b0 * b0) * np.einsum("ik,ik->i", powers * _K12, mom[:, 2:n + 2])
    return x0, x1, x2


_SERIES_ORDER = 22  # at most the Taylor terms k = 0 .. 22 of exp(-y/b) around a node (X_0)
_SERIES_TOL = 1e-17  # truncation bound per unit of |weight| (below an ulp of the values)
_SERIES_RADIUS = 0.15  # the series serves |log b - log b_node| <= this
_K1 = np.arange(1.0, _SERIES_ORDER + 2.0)  # k + 1, k = 0 .. N
_K12 = _K1 * (_K1 + 1.0)  # (k + 1)(k + 2)


def _cheb_terms(x_cap: float, tol: float) -> int:
    """The least number m of Chebyshev points whose polynomial interpolant of ``y^j
    exp(-y/b)``, ``j = 0, 1, 2``, on ``[0, y_max]`` is within ``tol b^j max(1, x)^j`` for
    every ``b >= y_max / x_cap`` (``x = y_max / b``), per unit of weight: interpolation at
    the m Chebyshev points of an interval of length L errs by at most ``L^m / (2^(2m-1) m!)
    max |f^(m)|``, here ``b^j 2 (x/4)^m / m! max_{z <= x} |d^m/dz^m (z^j e^-z)|`` and
    ``|d^m/dz^m (z^2 e^-z)| = |z^2 - 2 m z + m (m - 1)| e^-z <= (x + m)^2`` (which bounds
    ``j = 0, 1`` too, relative to ``max(1, x)^j``)."""
    log_tol = math.log(tol)
    for m in range(1, 400):
        factor = 2.0 * math.log((x_cap + m) / max(1.0, x_cap))
        if math.log(2.0) + m * math.log(x_cap / 4.0) - math.lgamma(m + 1) + factor <= log_tol:
            return m
    raise ValueError(f"no Chebyshev interpolant for x_cap={x_cap}")


# The Chebyshev moments serve b >= max(y) / _CHEB_X (below: Taylor nodes). Their rounding is
# absolute, ~3e-15 per unit of |weight| in E_i[y^j exp(-y/b)] (the interpolant's terms are O(1)
# where exp(-y/b) is as small as exp(-_CHEB_X)), so relative to E_i[exp(-y/b)] it grows like
# exp(_CHEB_X): 6 keeps it below ~1.2e-12 (the objective's relative error below ~2e-13) for a
# factor whose mass sits at the largest value. Exact distributions (non-negative operators,
# the exact evaluation) keep the Taylor nodes, relatively accurate to rounding.
_CHEB_X = 6.0
_CHEB_STEP = _LOCAL_STEP  # spacing (in log b) of the grid points added across that range
_CHEB_TERMS = _cheb_terms(_CHEB_X, _SERIES_TOL)
_CHEB_S = np.cos(np.pi * (np.arange(_CHEB_TERMS) + 0.5) / _CHEB_TERMS)  # Chebyshev points
# c = _CHEB_MATRIX @ f(points): the coefficients of the interpolant sum_k c_k T_k
_CHEB_MATRIX = (2.0 / _CHEB_TERMS) * np.cos(
    np.pi * np.outer(np.arange(_CHEB_TERMS), np.arange(_CHEB_TERMS) + 0.5) / _CHEB_TERMS)
_CHEB_MATRIX[0] *= 0.5


# ---------------------------------------------------------------------------------- chi^2 ball

__all__ += ["chi2_constrained"]


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
