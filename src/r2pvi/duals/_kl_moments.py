"""The KL-ball objective's moments: on a grid of ``b`` (one operator call), per factor (the
explicit weight rows), from Chebyshev moments, from Taylor moments at a few nodes.

:class:`_KLMoments` is the evaluation half of :class:`~r2pvi.duals._kl_ball._KLProblem`: it
turns moments ``E_i[y^k exp(-y/b)]`` into the objective through the problem's
``_objective`` and ``_plain`` (the formulas, with the clip to Jensen's floor), and reads the
problem's state (``E``, ``v``, ``dims``, ``shift``, ``norm``, ``base``, ``rho``, ``cap``,
``scale``, the Chebyshev range) set by its constructor.
"""

from __future__ import annotations

import math

import numpy as np

from ._kl_series import (
    _CHEB_MATRIX,
    _CHEB_STEP,
    _CHEB_TERMS,
    _EXPM1_FROM,
    _SERIES_ORDER,
    _SERIES_RADIUS,
    _series_moments,
    _series_order,
)
from ._scratch import buffer


class _KLMoments:
    """Objective and t-derivatives of the KL-ball dual at given ``b``, from the moments."""

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

    def _grid_eval(self, bs, state, moments=None):
        """:meth:`on_grid` from the columns of :meth:`_grid_fill` (one operator call), or from
        their ``moments`` (the operator applied to them) when already known."""
        cols, plain, cheb, j_all, n_basis, ones = state
        out = [np.empty((self.dims.size, bs.size)) for _ in range(3)]
        if cols is not None:
            mom = (self.E(cols) if moments is None else moments)[self.dims]
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
            factors = self.E.weight_factors()
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
            for i in k:  # C_k = C_{k-1} y / (k b) (a loop of rows: accumulate is slower)
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
