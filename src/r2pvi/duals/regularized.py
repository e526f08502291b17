"""Duals of the regularized problem ``inf_mu E_mu V + lam D(mu || mu0)``, one per factor.

Every function takes an expectation operator ``E`` (d factors over n points), the values
``v (n,)`` at those points and ``lam > 0``, and returns the d dual values ``w (d,)``.
With a :class:`~r2pvi.duals.RidgeExpectation` they are the paper's estimators; with a
:class:`~r2pvi.duals.FactorExpectation` they are the exact robust-regularized expectations.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from ._scratch import buffer
from ._valid_moments import RowScaled, effective_counts, floor_masses
from .operator import ExpectationOperator, FactorExpectation
from .piecewise import blockwise_max, dense_max
from .ranges import value_extent

__all__ = [
    "tv_regularized", "kl_regularized", "chi2_regularized", "row_sums",
    "KL_FORMS", "MOMENTS",
]

_TINY = 1e-250
# kl_regularized: expm1 (instead of exp(z) - 1) once lam exceeds this many value spreads.
_EXPM1_FROM = 64.0
# kl_regularized: the centered moment (not the moment) is regressed above this many spreads.
_CENTER_FROM = 1.0


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


def row_sums(E: ExpectationOperator) -> np.ndarray:
    """``s_i = sum_j M_ij``, the total weight of each factor: 1 for a true-model operator (its
    rows are distributions), ``[Lambda^-1 Phi^T 1]_i`` for a ridge operator (below 1 by ridge
    shrinkage on the simplex, possibly above with overlapping features)."""
    return E.total_weights()


KL_FORMS = ("normalized", "paper")
MOMENTS = ("valid", "ridge")


def kl_regularized(E: ExpectationOperator, v: np.ndarray, lam: float, v_max=None,
                   form: str = "normalized", *,
                   extent: tuple[float, float] | None = None,
                   moments: str = "ridge") -> np.ndarray:
    """KL: ``-lam log E_i[exp(-V/lam)]`` (paper, Prop. KL duality and eq. (KL-estimation)).

    ``form="normalized"`` (default) estimates each factor as the ridge regression estimates
    any expectation: ``s_i`` times the exact dual under the row-normalized weights
    ``M_i / s_i`` (``s_i = sum_j M_ij``, see :func:`row_sums`),

        w_i = s_i * (c - lam log(E_i[exp(-(V - c)/lam)] / s_i)),    c = min V,

    which is the dual itself for a distribution (``s_i = 1``). It tends to the plain ridge
    estimate ``E_i(V)`` as ``lam -> inf`` and to ``s_i`` times the smallest value of the
    factor's sample as ``lam -> 0``. ``form="paper"`` is the paper's literal
    ``-lam log max{w'_i, exp(-V_max/lam)}``, ``w'_i`` the ridge estimate of
    ``E_i[exp(-V/lam)]``: as ridge weights sum to ``s_i < 1`` it carries a bias of about
    ``-lam log s_i`` that grows without bound with ``lam``.

    ``v_max`` is the upper bound on V (the floor ``exp(-V_max/lam)`` of the paper's form, a cap
    ``w_i <= V_max`` in both forms); None takes the maximum of ``v``. In the normalized form a
    ridge operator's estimate is capped at the plain estimate ``E_i(v)``, its ``lam -> inf``
    limit, which the exact dual never exceeds: with signed ridge weights the formula can pass
    it, and a tiny or non-positive moment (a negative weight at the least values) makes it
    tend to ``+inf``, where the cap gives ``E_i(v)`` (continuously). ``E_i(v)`` comes from the
    moment's own pass (one product of the stacked vectors,
    :meth:`~r2pvi.duals.ExpectationOperator.pair_with_total_weights`). Distributions are not
    capped (their dual is at most ``E V``). ``extent``: ``(min v, max v)`` when already known
    (:func:`~r2pvi.duals.ranges.value_extent`), to save two passes over ``v``.

    ``moments="valid"`` (R2PVI's default; normalized form, ridge operators): the normalized
    moment ``u_i / s_i`` is clipped to ``[max(f_i, e^{-(max v - c)/lam}), 1]``, the range of
    the moment of a distribution on the values with at least ``f_i = 1 / (1 + N_i)`` of its
    mass at ``c`` (``N_i = s_i^2 / [Lambda^-1]_ii``, the factor's effective count;
    :mod:`r2pvi.duals._valid_moments`): the paper's floor ``exp(-H/lam)`` raised to what the
    data resolve, so ``s_i c <= w_i <= s_i (c + lam log(1 + N_i))`` (and at most ``E_i(v)``)
    where the ridge moment is <= 0 or tiny. ``"ridge"`` (default here): the moment as regressed.
    Non-negative operators are unchanged either way.

    Monotonicity in ``lam``: for a distribution, and for a ridge factor whose weights are all
    non-negative (its normalized weights are a distribution), the estimate is the exact dual
    (times ``s_i``), non-decreasing in ``lam``. With signed weights it need not be: the
    derivative of ``-lam log E_p[e^{-y/lam}]`` in ``lam`` is ``sum_j p_j r_j log r_j`` with
    ``r_j = e^{-y_j/lam} / E_p[e^{-y/lam}] > 0`` and ``sum_j p_j r_j = 1``, which is
    ``KL >= 0`` for ``p >= 0`` (Jensen) and can be negative when some ``p_j < 0``; a factor
    with negative weight at the least values has a pole (the moment crosses 0) and, above it,
    a dip below its ``lam -> inf`` limit. Making the estimate monotone would take its values
    at every larger ``lam`` (the running minimum over ``[lam, inf)``), many regressions per
    step; see docs/numerical-guarantees.md.
    Computed in the log domain, shifted by the minimum value, so it is finite and exact for
    ``lam`` from 1e-3 to 1e3 and beyond; factors whose shifted estimate underflows are
    recomputed by a sign-aware log-sum-exp over their explicit weights.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.duals import FactorExpectation, kl_regularized
    >>> E = FactorExpectation(np.array([[0.5, 0.5]]))
    >>> kl_regularized(E, np.array([0.0, 3.0]), lam=1e-3)   # -> min V as lam -> 0
    array([0.00069315])
    """
    if form not in KL_FORMS:
        raise ValueError(f"form must be one of {KL_FORMS}, got {form!r}")
    if moments not in MOMENTS:
        raise ValueError(f"moments must be one of {MOMENTS}, got {moments!r}")
    v = np.asarray(v, dtype=float)
    shift, upper_v = value_extent(v) if extent is None else extent
    upper = upper_v if v_max is None else float(v_max)
    # one K-sized work array (reused across steps: no page faults), transformed in place
    z = np.subtract(v, shift, out=buffer("kl.z", v.shape))
    with np.errstate(over="ignore"):  # lam far below the values: -inf, e^z = 0 (exact)
        z *= -1.0 / lam
    if form == "paper":
        with np.errstate(under="ignore"):
            ex = np.exp(z, out=z)
        log_u = _log_moment(E, v, shift, lam, E(ex))
        return shift - lam * np.maximum(log_u, -(upper - shift) / lam)
    # The moment u = E(e^{-(V-c)/lam}), the row sums s = E(1) and the centered moment
    # um = E(e^{-(V-c)/lam} - 1) = u - s, from ONE regression: s = Lambda^-1 Phi^T 1 comes
    # with the Gram matrix (its column sums are accumulated with it and stored with the data:
    # a d x d solve, no pass over the points; for rows validated to sum to 1 the row sums of
    # the Gram matrix, Phi^T Phi 1_d, whose difference Phi^T (1 - Phi 1_d) moves s_i by at most
    # 16 2^-52 sum_j |M_ij|: StepSource.unit_rows), and the regression is of whichever of the two
    # moments keeps the error of the other small. Up to lam = 1 value spread, u (then
    # um = u - s, used by the log1p form only where u > s/2, so its absolute error ~2^-53
    # sum_j |M_ij| (u + s) moves w_i by about lam 2^-53 sum_j |M_ij| / s_i: at most one
    # spread times that); above, um (then u = um + s, whose relative error is that of s):
    # regressing u there would leave um = u - s with an error growing like lam / spread,
    # past the bound. um is regressed on
    # e^z - 1, or on expm1(z) from lam = 64 spreads on, where every z is near 0 and e^z - 1
    # would carry the absolute rounding error of e^z (where |e^z - 1| >= 1/2 the subtraction
    # is exact anyway). tests/test_kl_one_regression.py checks both forms against the
    # two-regression one (u and um both regressed) under this bound.
    # (From 64 spreads on, every z >= -1/64, so e^z > 1/2 and expm1 applies everywhere.)
    spread = upper_v - shift
    # Ridge weights (signed): the plain estimate E(v) too, in the same pass as the moment (one
    # product of the stacked vectors): the cap below. Distributions never exceed E V.
    ridge = not E.nonnegative

    def regress(y):
        if ridge:
            return E.pair_with_total_weights(y, v)
        moment, total = E.with_total_weights(y)
        return moment, None, total

    if lam <= _CENTER_FROM * spread:
        with np.errstate(under="ignore"):
            u, plain, s = regress(np.exp(z, out=z))
        um = u - s
    else:
        if lam > _EXPM1_FROM * spread:
            np.expm1(z, out=z)
        else:
            np.exp(z, out=z)
            z -= 1.0
        um, plain, s = regress(z)
        u = um + s
    if s.min() > 0.0 and u.min() >= _TINY:  # the usual case, with d-sized operations only
        # log(u/s) = log1p(um/s): the accurate form when u/s is not small; log(u) - log(s)
        # where it is (both evaluated then; the unused one may be -inf)
        near_one = u > 0.5 * s
        if near_one.all():
            log_norm = np.log1p(um / s)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                log_norm = np.where(near_one, np.log1p(um / s), np.log(u) - np.log(s))
        live = None
    else:
        live = s > 0.0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            safe_s = np.where(live, s, 1.0)
            log_norm = _log_moment(E, v, shift, lam, u) - np.log(safe_s)
            # log(u/s) = log1p(um/s): the accurate form when u/s is not small
            near_one = u > 0.5 * safe_s
            log_norm[near_one] = np.log1p(um[near_one] / safe_s[near_one])
    if ridge and moments == "valid":
        _floor_log_moment(E, log_norm, s, spread / lam)
    with np.errstate(over="ignore", invalid="ignore"):
        w = s * (shift - lam * log_norm)  # +inf where the moment is <= 0 (ridge moments)
    if live is not None and not live.all():
        # no positive total weight: nothing to normalize, the plain estimate
        plain = E(v) if plain is None else plain
        w = np.where(live, w, plain)
    if plain is not None:
        # At most the plain estimate, the lam -> inf limit (the exact dual never exceeds E V):
        # where the moment is <= 0 (+inf above) the plain estimate itself.
        np.minimum(w, plain, out=w)
    return np.minimum(w, upper, out=w)


def _floor_log_moment(E, log_norm, s, x):
    """Clip the normalized log moments ``log(u_i / s_i)`` of the factors with ``s_i > 0`` to
    ``[max(log f_i, -x), 0]`` in place: ``e^{-x}`` (``x = (max V - c)/lam``) and 1 are the
    least and largest moments of a distribution on the values, ``f_i`` the floor of
    :func:`~r2pvi.duals._valid_moments.floor_masses`."""
    live = s > 0.0
    if not live.any():
        return
    np.minimum(log_norm, 0.0, out=log_norm, where=live)
    floor = np.maximum(np.log(floor_masses(E, s)), -x)
    np.maximum(np.nan_to_num(log_norm, nan=-np.inf), floor, out=log_norm, where=live)


def _log_moment(E, v, shift, lam, u):
    """``log E_i[exp(-(V - shift)/lam)]`` from its estimate ``u`` (``-inf`` where <= 0)."""
    # A clearly negative (ridge) estimate gets -inf; only estimates too small in magnitude
    # to trust after the global shift are recomputed exactly in the log domain.
    small = np.abs(u) < _TINY
    log_u = np.full_like(u, -np.inf)
    np.log(u, out=log_u, where=u >= _TINY)
    if small.any():
        dims = np.flatnonzero(small)
        rows = E.rows(dims)
        # A factor with no weight at all (e.g. a feature no sample activates) keeps -inf;
        # only factors with weight need the exact log-sum-exp.
        live = np.any(rows != 0.0, axis=1)
        if live.any():
            with np.errstate(over="ignore"):  # -inf: no mass there (exact)
                lse, sign = logsumexp(-(v - shift) / lam, b=rows[live], axis=1,
                                      return_sign=True)
            log_u[dims[live]] = np.where(sign > 0, lse, -np.inf)
    return log_u


def chi2_regularized(
    E: ExpectationOperator,
    v: np.ndarray,
    lam: float,
    mean_clip: tuple[float, float] | None = None,
    second_clip: tuple[float, float] | None = None,
    method: str = "auto",
    center: bool = True,
    extent: tuple[float, float] | None = None,
    moments: str = "ridge",
) -> np.ndarray:
    """chi^2: ``max_alpha E_i[V]_alpha + (E_i[V]_alpha)^2/(4 lam) - E_i[V^2]_alpha/(4 lam)``.

    The paper's eq. (parameter estimation x2), maximized exactly over ``alpha`` in
    ``[min v, max v]`` for each factor, with the optional clipping of the first and second
    moment estimates to ``mean_clip = (0, H)`` and ``second_clip = (0, H^2)``
    (eqs. (estimation of EV / EV2 in chi2)). With a true-model operator and no clipping this
    is ``max_alpha E[V]_alpha - Var[V]_alpha / (4 lam)`` (Prop. chi^2 duality).

    ``center=True`` (default) computes the moments of the shifted values ``U = V - c``,
    ``c = min v``, and returns ``E_i(c) + (the same maximum for U)``: identical for
    distributions (``[V]_alpha = c + [U]_{alpha - c}``), but the variance is no longer the
    difference of two large numbers, so constant values return the constant exactly; the
    clips then apply to the moments of ``U`` (pass ``(0, V_max - c)`` and
    ``(0, (V_max - c)^2)``). On a true-model operator (rows are distributions) and without
    clips each factor is centered at the smallest value ``m_i`` of its own support (where the
    maximizer sits as ``lam -> 0``), and the result is kept in the interval the exact dual
    provably lies in,
    ``[m_i, min(E_i V, m_i + lam (1/p_i - 1))]`` with ``m_i`` the smallest value on the
    support of factor i and ``p_i`` its mass (the point mass at ``m_i`` costs
    ``lam chi^2 = lam (1/p_i - 1)``): for ``lam`` below the resolution of the values (down
    to 1e-300) that interval is the answer. ``center=False`` is the literal computation.
    ``extent``: ``(min v, max v)`` when the caller has them
    (:func:`~r2pvi.duals.ranges.value_extent`), to save passes over ``v``.

    ``moments="valid"`` (R2PVI's default; ridge operators, ``center=True``): ``s_i`` times the
    exact maximum for the normalized weights ``M_i / s_i`` (the ridge form uses ``M_i``
    itself, whose variance ``E_i(V^2) - E_i(V)^2`` is off by ``(s_i - s_i^2) E(V)^2`` when
    ``s_i != 1``), at most ``s_i (c + lam N_i)``, the largest dual of a distribution with mass
    ``1 / (1 + N_i)`` at ``c`` (``N_i`` as in :func:`kl_regularized`), and at most ``E_i(v)``;
    a factor whose value at the block starts reaches that cap is not searched further.
    ``"ridge"`` (default here): the moments of ``M_i``. Non-negative operators are unchanged.

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
    >>> chi2_regularized(E, np.full(2, 1e9), lam=1e-300)             # constants exactly
    array([1.e+09])
    """
    if method == "auto":
        method = "blockwise" if np.size(v) >= 512 else "dense"
    if method not in ("dense", "blockwise"):
        raise ValueError(f"method must be 'auto', 'dense' or 'blockwise', got {method!r}")
    if moments not in MOMENTS:
        raise ValueError(f"moments must be one of {MOMENTS}, got {moments!r}")
    v = np.asarray(v, dtype=float)
    if center and E.nonnegative and mean_clip is None and second_clip is None:
        # True-model operator: center each factor at the smallest value of its own support,
        # where the maximizer sits for small lam (prefix sums then hold no large values).
        mu = E.rows()
        m = np.where(mu > 0.0, v[None, :], np.inf).min(axis=1)
        w = np.empty(E.n_dims)
        for g in np.unique(m):
            rows = np.flatnonzero(m == g)
            sub = E if rows.size == E.n_dims else FactorExpectation(mu[rows])
            w[rows] = g + _chi2_core(sub, v - g, lam, None, None, method)
        return _within_exact_chi2_bounds(E, v, lam, w)
    lo_v, hi_v = value_extent(v) if extent is None else extent
    c = lo_v if center else 0.0
    totals = {}
    u = v - c if center else v
    if center and not E.nonnegative and moments == "valid":
        return _chi2_valid(E, u, c, lam, mean_clip, second_clip, method, (0.0, hi_v - c))
    # (v - c) rounds monotonically: its extent is the extent of v, shifted and rounded
    w = _chi2_core(E, u, lam, mean_clip, second_clip, method, totals, (lo_v - c, hi_v - c))
    # At most the plain estimate E_i(v), the objective's value at mu = mu0 (the exact dual
    # never exceeds E V; with signed ridge weights the estimated variance can be negative and
    # the maximum above it): E_i(u) and E_i(1) from the block sums when the branch and bound
    # ran (no further pass), shifted back like w (so constant values stay exact).
    exact = E.nonnegative and mean_clip is None and second_clip is None
    plain = None if exact else (totals["mean"] if "mean" in totals else E(u))
    if center and c != 0.0:
        mass = 1.0 if E.nonnegative else (
            totals["mass"] if "mass" in totals else row_sums(E))
        w = w + c * mass
        if plain is not None:
            plain = plain + c * mass
    if exact:
        return _within_exact_chi2_bounds(E, v, lam, w)
    return np.minimum(w, plain)


def _chi2_valid(E, u, c, lam, mean_clip, second_clip, method, extent):
    """:func:`chi2_regularized` of a ridge operator with ``moments="valid"``: ``s_i`` times the
    exact dual of the normalized weights ``M_i / s_i`` (the operator with rows scaled by
    ``1 / s_i``; centered values ``u = v - c >= 0``), kept at most ``s_i lam N_i`` (the largest
    dual of a distribution with mass ``f_i = 1 / (1 + N_i)`` at its least value; factors that
    reach it are not searched further) and at most the plain estimate, which a factor without
    positive total weight gets; plus ``c s_i``."""
    s = row_sums(E)
    live = s > 0.0
    k = np.where(live, 1.0 / np.where(live, s, 1.0), 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        ceiling = np.where(live, lam * effective_counts(E, s), np.inf)
    totals = {}
    w = _chi2_core(RowScaled(E, k), u, lam, mean_clip, second_clip, method, totals, extent,
                   ceiling)
    mean = totals.get("mean")
    plain = E(u) if mean is None or not live.all() else mean * s  # E_i(u)
    w = np.where(live, s * w, plain)
    return np.minimum(w, plain) + c * s


def _chi2_core(E, u, lam, mean_clip, second_clip, method, totals=None, extent=None,
               ceiling=None):
    """The exact maximum over alpha for values ``u`` (see :func:`chi2_regularized`);
    ``totals`` as in :func:`~r2pvi.duals.piecewise.blockwise_max` (blockwise only);
    ``extent``: ``(min u, max u)`` if known; ``ceiling (d,)``: the result is at most it."""
    lo_v, hi_v = value_extent(u) if extent is None else extent
    # E([V]^2_alpha) = C + B alpha^2 is monotone on a segment that does not contain alpha = 0.
    extra = (0.0,) if lo_v < 0.0 < hi_v else ()
    # For lam far below the values' resolution the quadratic term overflows: +-inf, and the
    # exact bounds (or the rule's range) take over.
    with np.errstate(over="ignore", invalid="ignore"):
        if method == "dense":
            w = dense_max(E, u, lam, mean_clip, second_clip, extra)
            return w if ceiling is None else np.minimum(w, ceiling)
        return blockwise_max(E, u, lam, mean_clip, second_clip, extra, totals,
                             ceiling=ceiling)


def _within_exact_chi2_bounds(E, v, lam, w):
    """``w`` kept in ``[m_i, min(E_i V, m_i + lam (1/p_i - 1))]`` (true-model operators)."""
    mu = E.rows()
    on = mu > 0.0
    m = np.where(on, v[None, :], np.inf).min(axis=1)
    p = np.where(on & (v[None, :] == m[:, None]), mu, 0.0).sum(axis=1)
    with np.errstate(over="ignore"):
        top = np.minimum(E(v), m + lam * (1.0 / p - 1.0))
    top = np.maximum(top, m)
    return np.minimum(np.maximum(np.nan_to_num(w, nan=-np.inf), m), top)
