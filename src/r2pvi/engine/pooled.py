"""What a pooled fit (``time_homogeneous=True``) computes once, and its rows as a linear map.

Pooled steps regress on the same rows at every step, with one Gram matrix: the operator is
formed once, and so is the pessimism penalty at every pooled next state (it depends only on
``Lambda^{-1}``); each step then costs one product with the next-state rows (the values) and
one with the taken-action rows (the rule's regressions). With state features stored once per
observation (:class:`~r2pvi.data.storage.crossed.CrossedRows`) both products read ``psi``:
:class:`CrossedRidgeExpectation` is the ridge operator of such rows, never forming them until
a rule asks for explicit rows.
"""

from __future__ import annotations

import numpy as np

from ..data.storage._finite import check_next_products
from ..data.storage.crossed import CrossedRows
from ..data.storage.sparse_rows import flat_rows
from ..duals.crossed_blocks import blocks_from_crossed
from ..duals.gram import GramFactor, ridge_cholesky
from ..duals.operator import RidgeExpectation
from ..duals.sorting import sort_breakpoints
from .penalty import penalty_values
from .q import _max_over_actions

__all__ = ["CrossedRidgeExpectation", "next_penalty", "PooledNextValues", "converged"]

#: A dual that refines more than this share of the sorted blocks has every block's sums kept
#: from then on (measured: DRPVI refines about 60 % of them, chi^2 under 2 %).
KEEP_SHARE = 0.25

# Consecutive pooled steps whose weights differ by at most this (relative to the largest
# weight, at least 1) are a fixed point: the fit copies them to the remaining steps.
STOP_RTOL = 1e-10


class _Rows:
    """The shape of rows an operator does not hold."""

    def __init__(self, shape):
        self.shape = shape


class CrossedRidgeExpectation(RidgeExpectation):
    """The ridge operator ``E(y) = Lambda^{-1} Phi^T W y`` of crossed rows
    ``phi(s, a) = e_a (x) psi(s)`` (:class:`~r2pvi.data.storage.crossed.CrossedRows`).

    ``Lambda`` (block diagonal) and ``E(y)`` read ``psi`` once each, in float64 chunks; the
    sorted blocks of the piecewise duals (chi^2, DRPVI) gather ``psi`` rows in sorted order
    (:meth:`sorted_blocks`); rules that need explicit weight rows (DRVI-L) reach for
    :attr:`phi`, which forms the ``(n, d)`` float64 rows once and from then on behaves as
    :class:`~r2pvi.duals.RidgeExpectation`.

    Examples
    --------
    >>> from r2pvi.data.storage.crossed import cross_rows
    >>> rng = np.random.default_rng(1)
    >>> psi, acts = rng.random((40, 3)), rng.integers(0, 2, 40)
    >>> E = CrossedRidgeExpectation(CrossedRows(psi, acts, 2), gamma=1.0)
    >>> x, y = cross_rows(psi, acts, 2), rng.random(40)
    >>> bool(np.allclose(E(y), np.linalg.solve(x.T @ x + np.eye(6), x.T @ y)))
    True
    """

    def __init__(self, rows: CrossedRows, gamma: float, weights=None,
                 nonnegative_features=None):
        self.crossed, self.gamma = rows, float(gamma)
        self._dense = None
        self._keep_blocks = False  # keep every sorted block's sums (see _refined)
        super().__init__(_Rows(rows.shape), None, weights, nonnegative_features)

    def _hold(self, phi, chol) -> None:
        gram = self.crossed.gram(self.weights)
        self.factor = GramFactor.from_cholesky(phi, ridge_cholesky(gram, self.gamma),
                                               self.weights, self.gamma)
        self.chol = self.factor.chol
        self.primal_dense = True

    @property
    def phi(self) -> np.ndarray:
        """The ``(n, d)`` float64 rows, formed once (for rules that need explicit rows)."""
        if self._dense is None:
            self._dense = self.crossed.dense()
            self.factor.phi = self._dense
        return self._dense

    def _sums(self, y) -> np.ndarray:
        return self.crossed.rmatmul(y, self.weights)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        if self._dense is not None:
            return super().__call__(y)
        sums = self._sums(y)
        return self._solve_sums(sums) if sums.ndim == 1 else self.factor.solve(sums)

    def apply_pair(self, y1, y2):
        if self._dense is not None or np.ndim(y1) != 1 or np.ndim(y2) != 1:
            return self(y1), self(y2)
        both = self.factor.solve(self._sums(np.stack([y1, y2], axis=1)))
        return both[:, 0].copy(), both[:, 1].copy()

    def pair_with_total_weights(self, y1, y2):
        e1, e2 = self.apply_pair(y1, y2)
        return e1, e2, self.total_weights()

    def total_weights(self) -> np.ndarray:
        if self._total is None:
            self._total = self._solve_sums(self.crossed.colsums(self.weights))
        return self._total.copy()

    def sorted_blocks(self, v, breakpoints_extra=(), moments: int = 3, group: int = 1):
        """:meth:`~r2pvi.duals.RidgeExpectation.sorted_blocks` from ``psi`` and the actions in
        sorted order (:func:`~r2pvi.duals.crossed_blocks.blocks_from_crossed`): the ``(n, d)``
        rows are not formed, nor ``psi`` in sorted order (a batch of blocks at a time)."""
        if self._dense is not None:
            return super().sorted_blocks(v, breakpoints_extra, moments, group)
        rows = self.crossed
        alphas, src, m = sort_breakpoints(v, breakpoints_extra)
        acts = np.take(rows.actions, src, mode="clip")
        if m < src.size or len(breakpoints_extra):  # extras and padding: zero rows
            acts[src < 0] = -1
        scale = None if self.weights is None else np.take(self.weights, src, mode="clip")
        if self.nonnegative_features is None:
            self.nonnegative_features = bool(rows.nonnegative())
        nonneg = self.nonnegative_features and self.weights is None
        linv = self.chol_inverse
        return blocks_from_crossed(alphas, rows.psi, src, acts, m, linv.T @ linv, nonneg,
                                   moments, group, scale, keep=self._keep_blocks,
                                   refined=self._refined)

    def _refined(self, share: float) -> None:
        """A dual refined ``share`` of the sorted blocks: when it is large, later calls keep
        every block's sums rather than form the refined ones again (see
        :func:`~r2pvi.duals.crossed_blocks.blocks_from_crossed`)."""
        if share > KEEP_SHARE:
            self._keep_blocks = True

    def gram_diagonal_and_sums(self):
        """``(diag(Phi^T W Phi), Phi^T W 1, non-empty rows, their total weight)`` for the fit's
        diagnostics, from the factor and the rows' column sums."""
        chol = self.chol
        diag = np.einsum("ij,ij->i", chol, chol) - self.gamma
        sums = self.crossed.colsums(self.weights)
        used = self.crossed.used()
        count = int(np.count_nonzero(used))
        total = float(count) if self.weights is None else float(self.weights[used].sum())
        return diag, sums, count, total


def next_penalty(feats, kind: str, beta: float, inv_diag, ellip) -> np.ndarray | None:
    """``Gamma(phi(s', a))`` at every pooled next state and action ``(n, A)`` (None when
    ``beta = 0``): computed once per fit, as every pooled step shares ``Lambda``."""
    if beta == 0.0:
        return None
    if isinstance(feats, CrossedRows):
        return feats.map_dense(lambda x: penalty_values(x, kind, beta, inv_diag, ellip))
    return penalty_values(feats, kind, beta, inv_diag, ellip)


class PooledNextValues:
    """``V_{h+1}`` at the pooled next states, step after step: the rows, their known values
    and the penalty (formed once per factor: :func:`next_penalty`) are kept; a step costs one
    product ``phi(s', a)^T w`` (with state features: ``psi(s') W``).

    Known values of episodes whose rewards were shifted by ``c`` (``reward_offset``) hold
    ``(H - h - 1) c`` for their row's step ``h``; at the pooled fit's step ``h'`` they are
    ``(H - h' - 1) c`` (the value of the shifted rewards still to come), so that the shift
    adds exactly ``(H - h') c`` to ``Q_h'`` as in a per-step fit. ``n_trajectories`` (K)
    gives a row's step (rows are step-major)."""

    def __init__(self, feats, known, check: bool, offset: float = 0.0, horizon: int = 1,
                 n_trajectories: int = 1):
        self.feats, self.check, self.known = feats, bool(check), known
        self.pen = None
        self.rows = None
        self.offset, self.horizon = float(offset), int(horizon)
        if known is not None:  # the rows holding a known value: few (absorbing states)
            self.rows = np.flatnonzero(~np.isnan(known).all(axis=1))
            self.row_known = known[self.rows]
            if self.offset:  # without the shift still to come after the row's own step
                steps = self.rows // int(n_trajectories)
                self.row_known = self.row_known - ((self.horizon - steps - 1)
                                                   * self.offset)[:, None]

    @property
    def step_dependent(self) -> bool:
        """Whether known values change with the fit's step (shifted rewards)."""
        return bool(self.offset) and self.rows is not None and self.rows.size > 0

    def set_penalty(self, kind: str, beta: float, inv_diag, ellip) -> None:
        """Form the penalty of a (new) factor at every next state and action."""
        self.pen = next_penalty(self.feats, kind, beta, inv_diag, ellip)

    def __call__(self, weights_h: np.ndarray, upper: float, step: int = 0):
        """``(V (n,), clipped)``: ``V = max_a clip(phi(s', a)^T w - pen, 0, upper)``, known
        values where given; ``clipped`` says whether some value reached ``upper`` before the
        clip (then a larger bound would change it: no fixed point; rows with known values
        count too, which can only delay a stop)."""
        feats = self.feats
        if isinstance(feats, CrossedRows):
            q = feats.action_values(weights_h)
        else:
            flat, lead = flat_rows(feats)
            q = np.asarray(flat @ weights_h).reshape(lead)
        if self.pen is not None:
            q -= self.pen
        if self.check and isinstance(feats, np.ndarray):
            check_next_products(q, feats, self.known)
        v = _max_over_actions(q)
        clipped = bool(v.max(initial=-np.inf) >= upper)
        np.clip(v, 0.0, upper, out=v)  # max_a clip(q_a) = clip(max_a q_a)
        if self.rows is not None and self.rows.size:
            qk = np.clip(q[self.rows], 0.0, upper)
            known = self.row_known
            if self.offset:
                known = known + (self.horizon - step - 1) * self.offset
            v[self.rows] = np.where(np.isnan(known), qk, known).max(axis=1)
        return v, clipped


def converged(w: np.ndarray, w_next: np.ndarray) -> bool:
    """Whether two consecutive pooled steps' weights agree to :data:`STOP_RTOL`."""
    scale = max(1.0, float(np.max(np.abs(w_next), initial=0.0)))
    return float(np.max(np.abs(w - w_next), initial=0.0)) <= STOP_RTOL * scale
