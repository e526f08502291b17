"""The KL-ball dual's 1-D problem ``sup_{b > 0} -b log u_i(b) - b rho_i``, all factors at once.

:class:`_KLProblem` (used by :func:`~r2pvi.duals.kl_constrained`) holds each factor's shift,
row sums and cap and solves the problem in ``t = log b``: the objective, its first and second
derivatives on a log-spaced grid of ``b`` (one operator call for all factors) give each
factor a bracket around its best grid point and, as a first guess, the maximizer of the
quintic through the bracket's ends; a safeguarded Newton iteration (bisection when a step
leaves the bracket) refines it until its predicted gain is below 1e-14 of the values; the
best value seen is returned.

The moments come from :class:`~r2pvi.duals._kl_moments._KLMoments`. For ridge operators
(``y = V - min V``), the moments ``E_i[T_k(2 y / max y - 1)]`` of 24 Chebyshev polynomials,
read in the grid's operator call, give ``E_i[y^j exp(-y/b)]``, ``j = 0, 1, 2``, for every
``b`` in ``[max y / 6, max |V|)`` (interpolation at the Chebyshev points: truncation below
1e-17, rounding ~3e-15, per unit of weight): there the grid gets points 0.1 apart in ``log b``
and the Newton steps need no pass over the points. For smaller ``b`` (and for exact
distributions, whose evaluation stays accurate to rounding relative to ``u_i``) a few shared
nodes near the guesses keep the moments ``E_i[(y/b0)^k / k! exp(-y/b0)]`` (one operator
call), from which a Taylor series in ``b0/b - 1`` gives any factor's objective within
``|log(b/b0)| <= 0.15`` to 1e-17 per unit of weight; above the values' scale (or where
factors do not share their least value) grid points and Newton steps are evaluated directly.
Everything is computed in the log domain, shifted by the smallest value each factor can see,
with ``expm1`` for large ``b``.
"""

from __future__ import annotations

import numpy as np

from ._kl_moments import _KLMoments
from ._kl_series import _CHEB_S, _CHEB_X, _LOCAL_STEP, _hermite_argmax

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


class _KLProblem(_KLMoments):
    """The KL-ball dual of the factors ``dims``: its setup, the search in log b and the
    objective's formulas (the moments: :class:`~r2pvi.duals._kl_moments._KLMoments`)."""

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
        """The grid of log b and its transformed values (:meth:`_grid_fill`); returns the
        plain estimate ``E(v)``, asked for with the grid's columns (``E.apply_pair``: one pass
        over the points where the operator streams them)."""
        lo_b = b_min if b_min is not None else _B_FLOOR * self.scale
        hi_b = max(float(self.b_hi.max()), 4.0 * lo_b)
        tgrid = _log_grid(lo_b, hi_b, self.scale)
        state = self._grid_fill(np.exp(tgrid))
        if state[0] is None:
            plain, moments = self.E(self.v), None
        else:
            plain, moments = self.E.apply_pair(self.v, state[0])
        self._coarse = (tgrid, state, moments)
        return plain

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
        tgrid, state, moments = self._coarse
        g, dg, d2g = self._grid_eval(np.exp(tgrid), state, moments)
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
