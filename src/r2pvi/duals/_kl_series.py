"""The KL-ball solver's series and polynomials (pure functions and constants).

- the quintic Hermite interpolant through two grid points (values and two t-derivatives at
  both ends) and its maximizer, the solver's starting points (:func:`_hermite_argmax`);
- Taylor series of ``exp(-y/b)`` around a node ``b0``: the moments of any ``b`` near the node
  from those of the node (:func:`_series_moments`, :func:`_series_order`);
- Chebyshev interpolation of ``y^j exp(-y/b)`` on ``[0, max y]``: the moments of every ``b``
  in a range from the moments of the Chebyshev polynomials (:func:`_cheb_terms`).
"""

from __future__ import annotations

import math

import numpy as np


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
