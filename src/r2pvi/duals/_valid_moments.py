"""Valid moment estimates on learned data: every factor keeps a mass of order ``1/N_i`` at the
least value (``moments="valid"`` of :func:`~r2pvi.duals.kl_regularized` and
:func:`~r2pvi.duals.chi2_regularized`; docs/user_guide/rare-events.md).

A ridge factor's weights ``M_i`` are signed. The KL moment ``E_i[exp(-(V - c)/lam)]`` and the
chi^2 variance of ``[V]_alpha`` are then estimates that can leave their range (a moment <= 0, a
variance < 0), most of all where the values that matter are rare (a failure state reached by
a few transitions): the moment is then essentially the ridge estimate of a small probability.
The rule is the paper's own floor ``max{w', exp(-H/lam)}`` raised to what the data resolve:

- ``N_i``, the factor's effective count (:func:`effective_counts`): ``s_i^2 /
  [Lambda^-1]_ii`` for a regression (``s_i = sum_j M_ij``), about ``n_i`` for one-hot
  features seen ``n_i`` times, ``0`` for a factor without positive weight;
- ``f_i = 1 / (1 + N_i)``: the factor's normalized weights ``M_i / s_i`` are taken to hold at
  least ``f_i`` of their mass at the least value ``c = min V``.

KL clips the normalized moment to ``[max(f_i, e^{-(max V - c)/lam}), 1]``; chi^2 is ``s_i``
times the dual of ``M_i / s_i`` (:class:`RowScaled`), at most ``s_i (c + lam N_i)``, the
largest dual of a distribution with mass ``f_i`` at ``c``. Exact distributions (non-negative
operators) are unchanged.
"""

from __future__ import annotations

import numpy as np

from .operator import ExpectationOperator

__all__ = ["effective_counts", "floor_masses", "RowScaled"]

# Rows per chunk when the weights are read row by row.
_ROW_CHUNK = 16


def effective_counts(E: ExpectationOperator, s: np.ndarray, dims=None) -> np.ndarray:
    """``N_i`` of the factors ``dims`` (all when None; ``s`` their row sums ``E_i(1)``).

    A regression (an operator with ``inverse_diagonal``, the diagonal of ``Lambda^{-1}``):
    ``N_i = s_i^2 / [Lambda^{-1}]_ii``, the information the regression has on coefficient i in
    units of its row sum (``n_i^2 / (n_i + gamma)`` for one-hot features seen ``n_i`` times);
    ``sqrt([Lambda^{-1}]_ii)`` is the scale of the paper's bound on the coefficient's error
    (its penalty). Any other operator: the Kish count ``s_i^2 / sum_j M_ij^2`` of its weights
    (``N`` for ``N`` equal weights), a function of the weights alone. ``0`` where ``s_i <= 0``.
    """
    dims = np.arange(E.n_dims) if dims is None else np.asarray(dims, dtype=np.intp)
    s = np.asarray(s, dtype=float)
    scale = _inverse_diagonal(E)
    scale = _squared_weight_sums(E, dims) if scale is None else scale[dims]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        count = np.where((s > 0.0) & (scale > 0.0), s * s / np.where(scale > 0, scale, 1.0),
                         0.0)
    return count


def _inverse_diagonal(E):
    """``diag(Lambda^{-1})`` of a regression operator, None for other operators. (A primal
    factor built from a bare Cholesky factor has no gamma, which only the unused features of
    sparse rows need: the column norms of ``L^{-1}`` then.)"""
    inverse_diagonal = getattr(E, "inverse_diagonal", None)
    if inverse_diagonal is None:
        return None
    try:
        return np.asarray(inverse_diagonal(), dtype=float)
    except TypeError:
        factor = getattr(E, "factor", None)
        if factor is None or factor.form != "primal" or factor.cols is not None:
            raise
        linv = factor.linv
        return np.einsum("ij,ij->j", linv, linv)


def _squared_weight_sums(E: ExpectationOperator, dims: np.ndarray) -> np.ndarray:
    """``sum_j M_ij^2`` for the factors ``dims``, from the explicit rows, a few at a time."""
    out = np.zeros(dims.size)
    for k in range(0, dims.size, _ROW_CHUNK):
        rows = E.rows(dims[k:k + _ROW_CHUNK])
        out[k:k + _ROW_CHUNK] = np.einsum("ij,ij->i", rows, rows)
    return out


def floor_masses(E: ExpectationOperator, s: np.ndarray, dims=None) -> np.ndarray:
    """``f_i = 1 / (1 + N_i)`` (:func:`effective_counts`) of the factors ``dims``: 1 for a
    factor without positive weight."""
    return 1.0 / (1.0 + effective_counts(E, s, dims))


class RowScaled(ExpectationOperator):
    """``diag(k) M``: the operator ``E`` with row i scaled by ``k_i`` (for chi^2's mixture,
    whose centered moments are those of ``E`` times ``(1 - f_i) / s_i``). Every member the
    duals use is ``E``'s, scaled; sums of ``|M|`` by ``|k_i|``."""

    def __init__(self, E: ExpectationOperator, k: np.ndarray):
        self.E, self.k = E, np.asarray(k, dtype=float)
        self.n_dims, self.n_points = E.n_dims, E.n_points
        self.nonnegative = bool(E.nonnegative and (self.k >= 0).all())

    def _scale(self, x, dims=None):
        k = self.k if dims is None else self.k[dims]
        return x * (k if np.ndim(x) == 1 else k[:, None])

    def __call__(self, y):
        return self._scale(self.E(y))

    def rows(self, dims=None):
        if dims is None:
            return self._scale(self.E.rows())
        dims = np.atleast_1d(dims)
        return self._scale(self.E.rows(dims), dims)

    def apply_pair(self, y1, y2):
        a, b = self.E.apply_pair(y1, y2)
        return self._scale(a), self._scale(b)

    def total_weights(self):
        return self._scale(self.E.total_weights())

    def weight_factors(self):
        factors = self.E.weight_factors()
        if factors is None:
            return None
        psi, r = factors
        return psi, r * self.k[:, None]

    def truncation_cumulants(self, v, breakpoints_extra=()):
        cum = self.E.truncation_cumulants(v, breakpoints_extra)
        for name in ("a", "b", "c"):
            getattr(cum, name)[...] *= self.k[:, None]
        return cum

    def sorted_blocks(self, v, breakpoints_extra=(), moments: int = 3, group: int = 1):
        sb = self.E.sorted_blocks(v, breakpoints_extra, moments, group)
        k, ka = self.k, np.abs(self.k)
        sb.sums = sb.sums * k[None, :, None]
        sb.sabs = sb.sabs * ka[:, None]
        fine, pairs = sb.fine, sb.pairs

        def scaled_fine(rows, blocks):
            sums, sabs = fine(rows, blocks)
            return sums * k[rows][None, :, None], sabs * ka[rows][:, None]

        def scaled_pairs(rows, blocks):
            return pairs(rows, blocks) * k[rows][:, None]

        sb.fine, sb.pairs = scaled_fine, scaled_pairs
        return sb
