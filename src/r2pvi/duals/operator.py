"""Linear expectation operators ``E: R^n -> R^d``, the one thing every dual is written against.

Each dual of the paper is a formula in expectations of transformed values under the d
factor distributions ``mu_{h,i}``. An operator maps values ``y`` at n points (sampled next
states, or all states of a finite model) to the d expectations ``E(y)_i = sum_j M_ij y_j``:

- :class:`RidgeExpectation` — learning: ``M = Lambda^{-1} Phi^T W`` (ridge regression of
  ``y`` on the features, optionally variance-weighted by ``W = diag(w)``);
- :class:`FactorExpectation` — exact evaluation on a known model: ``M = mu_h`` (rows are the
  true factor distributions over a finite state space).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ._scratch import buffer
from .gram import GramFactor, cholesky_gram  # noqa: F401 - cholesky_gram: the doctests
from .sorting import (
    SortedBlocks,
    TruncationCumulants,
    blocks_from_features,
    blocks_from_weights,
    cumulants_from_weights,
    sort_breakpoints,
)

__all__ = ["ExpectationOperator", "RidgeExpectation", "FactorExpectation"]


class ExpectationOperator:
    """The interface every dual is written against: ``E(y) = M @ y``, ``M`` a (d, n) matrix
    whose row i holds factor i's weights over the n points.

    A subclass provides the first four members; the others have defaults built on them,
    which a subclass overrides only to compute the same numbers faster (e.g. the ridge
    operator in feature space, or an operator that streams its points reading them once
    for all the columns a call asks for). The duals use these members only, and never ask
    which kind of operator they hold:

    - ``n_dims``, ``n_points``: d and n.
    - ``nonnegative``: True when every weight is >= 0 (each row a distribution up to its
      total weight, e.g. the true factors); the duals then use the exact-distribution forms.
    - ``E(y)``: ``M @ y`` for ``y (n,)`` -> ``(d,)`` or ``(n, m)`` -> ``(d, m)``.
    - :meth:`rows`: explicit weights ``M[dims]``, ``(len(dims), n)``.
    - :attr:`matrix`: every row, computed once.
    - :meth:`total_weights`: ``E(1)`` ``(d,)``, the row sums ``s_i``.
    - :meth:`with_total_weights`, :meth:`apply_pair`, :meth:`pair_with_total_weights`:
      several expectations at once, ``(E(y), E(1))``, ``(E(y1), E(y2))`` and ``(E(y1),
      E(y2), E(1))``.
    - :meth:`truncation_cumulants`: ``E([V]_alpha)`` and ``E([V]_alpha^2)`` on every segment
      between sorted values (:class:`~r2pvi.duals.TruncationCumulants`).
    - :meth:`sorted_blocks`: block sums of the weights in sorted order, for the branch and
      bound of the piecewise duals (:class:`~r2pvi.duals.sorting.SortedBlocks`).
    - :meth:`weight_factors`: ``(psi (n, p), R (d, p))`` with ``M = R psi^T`` when the operator
      has that structure (rows formed by one product), else None.

    The sorted views' defaults go through :meth:`sorted_weights` and :meth:`weight_columns`
    (weight columns in sorted order), which a subclass may override instead.
    """

    n_dims: int
    n_points: int
    nonnegative: bool = False

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """Apply to ``y`` of shape (n,) -> (d,), or (n, m) -> (d, m)."""
        raise NotImplementedError

    def rows(self, dims=None) -> np.ndarray:
        """Explicit weights ``M[dims]`` of shape (len(dims), n); all rows when ``dims`` is None."""
        raise NotImplementedError

    def apply_pair(self, y1: np.ndarray, y2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y1), E(y2))`` for ``y1``, ``y2`` each ``(n,)`` or ``(n, m)``, in one pass over
        the points where the operator can."""
        return self(y1), self(y2)

    def total_weights(self) -> np.ndarray:
        """``E(1)``, the total weight ``s_i = sum_j M_ij`` of each factor ``(d,)``: 1 for a
        true-model operator (rows are distributions)."""
        if self.nonnegative:
            return np.ones(self.n_dims)
        return self(np.ones(self.n_points))

    def with_total_weights(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y), E(1))`` for ``y (n,)`` (a ridge operator keeps ``Phi^T W 1`` with its Gram
        matrix, so ``E(1)`` costs a ``d x d`` solve and no pass over the points)."""
        return self(y), self.total_weights()

    def pair_with_total_weights(self, y1: np.ndarray, y2: np.ndarray):
        """``(E(y1), E(y2), E(1))`` for two vectors ``(n,)``, in one pass over the points where
        the operator can (a ridge operator: one product of the stacked vectors, with the
        column sums when they are not known)."""
        e1, e2 = self.apply_pair(y1, y2)
        return e1, e2, self.total_weights()

    @property
    def matrix(self) -> np.ndarray:
        """The full (d, n) weight matrix (computed once, then cached)."""
        cached = getattr(self, "_matrix_cache", None)
        if cached is None:
            cached = self.rows()
            self._matrix_cache = cached
        return cached

    def weight_factors(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(psi (n, p), R (d, p))`` with ``M = R psi^T``, so that rows are one product
        ``R[dims] @ psi.T``; None when the operator has no such structure (then :meth:`rows`)."""
        return None

    def weight_columns(self, src: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Write the weight columns ``M[:, src]`` into ``out (d, len(src))``; a negative
        index gives a zero column (padding, extra breakpoints)."""
        np.take(self.matrix, np.maximum(src, 0), axis=1, out=out, mode="clip")
        out[:, src < 0] = 0.0
        return out

    def sorted_weights(self, v: np.ndarray, breakpoints_extra=(), key="sorted"):
        """Sort the breakpoints once: ``(alphas (p,), weights (d, p), m)``.

        ``alphas`` are ``v`` plus ``breakpoints_extra`` in increasing order, padded to a
        multiple of 16 by repeating the largest; ``weights[:, k]`` is the weight column of
        the point at ``alphas[k]`` (zero for extra breakpoints and padding); the first ``m``
        entries are the real breakpoints. ``weights`` is a reused work buffer.
        """
        alphas, src, m = sort_breakpoints(v, breakpoints_extra)
        weights = self.weight_columns(src, out=buffer(key, (self.n_dims, src.size)))
        return alphas, weights, m

    def sorted_blocks(self, v: np.ndarray, breakpoints_extra=(), moments: int = 3,
                      group: int = 1) -> SortedBlocks:
        """Block sums of the sorted weight columns, for branch and bound over breakpoints.

        Returns :class:`~r2pvi.duals.sorting.SortedBlocks` with ``alphas (p,)`` as in
        :meth:`sorted_weights` and, for every block of ``16 group`` consecutive sorted points
        (the last one may be shorter), the sums of ``M``, ``M v`` and (with ``moments=3``)
        ``M v^2``, and an upper bound on the sum of ``|M|`` (each ``(d, ceil(p / (16
        group)))``), plus functions giving the same sums on the blocks of 16 inside chosen
        (factor, block) pairs and the exact weights of chosen (factor, block of 16) pairs. The
        arrays may live in reused work buffers: valid until the next call in the same thread.
        """
        alphas, weights, m = self.sorted_weights(v, breakpoints_extra)
        return blocks_from_weights(alphas, weights, m, moments, group)

    def truncation_cumulants(self, v: np.ndarray, breakpoints_extra=()) -> TruncationCumulants:
        """Expectations of the truncated values ``[V]_alpha = min(V, alpha)`` for every alpha.

        Sorting ``v`` once, on segment k (``alpha`` between the k-th and (k+1)-th smallest
        breakpoint) ``E([V]_alpha) = A_k + B_k alpha`` and ``E([V]_alpha^2) = C_k + B_k alpha^2``
        with prefix sums ``A``, ``C`` and tail sums ``B`` of the weights: every breakpoint of a
        piecewise dual in O(n d) after one sort. ``breakpoints_extra`` adds alphas (with zero
        weight) that must separate segments. The arrays live in reused work buffers: they are
        valid until the next call in the same thread.
        """
        alphas, weights, m = self.sorted_weights(np.asarray(v, dtype=float), breakpoints_extra)
        return cumulants_from_weights(alphas, weights, m)


# Rows per chunk of RidgeExpectation.apply_pair: 1024 x 30 float64 = 240 kB, within L2.
_PAIR_CHUNK = 1024

class RidgeExpectation(ExpectationOperator):
    """Ridge-regression estimate of the factor expectations: ``E(y) = Lambda^{-1} Phi^T W y``.

    Parameters
    ----------
    phi : ndarray or scipy.sparse matrix (n, d)
        Features of the taken actions at this step.
    chol : ndarray (d, d) or GramFactor
        Lower Cholesky factor of ``Lambda = Phi^T W Phi + gamma I`` (see :func:`cholesky_gram`),
        or a :class:`GramFactor` (primal or dual form, dense or sparse features).
    weights : ndarray (n,), optional
        Sample weights ``w = 1 / sigma^2`` (variance-aware regression); None means 1.

    Examples
    --------
    >>> import numpy as np
    >>> phi = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    >>> E = RidgeExpectation(phi, cholesky_gram(phi, gamma=1e-12))
    >>> np.round(E(np.array([1.0, 5.0, 3.0])), 6)      # per-factor sample means
    array([2., 5.])
    >>> E2 = RidgeExpectation(phi, GramFactor(phi, 1e-6, form="dual"))   # Woodbury form
    >>> np.round(E2(np.array([1.0, 5.0, 3.0])), 4)
    array([2., 5.])
    """

    nonnegative = False

    def __init__(self, phi, chol, weights: np.ndarray | None = None,
                 nonnegative_features: bool | None = None):
        self.weights = weights
        self.nonnegative_features = nonnegative_features  # phi >= 0 (None: check when needed)
        self.n_points, self.n_dims = phi.shape
        self._total = None  # E(1), formed when first asked
        self._hold(phi, chol)

    def _hold(self, phi, chol) -> None:
        """Hold the rows and the factor of ``Lambda``. A subclass that streams its rows
        overrides this to form them when first asked (``phi``, ``factor``, ``chol`` and
        ``primal_dense`` are then its properties or attributes)."""
        self.phi = phi
        if isinstance(chol, GramFactor):
            self.factor = chol
        else:
            self.factor = GramFactor.from_cholesky(phi, chol, self.weights)
        self.chol = self.factor.chol
        # The fast feature-space paths below need dense rows and the primal factor; otherwise
        # the explicit (d x n) weight matrix, which the dual form gets for n^2 d flops.
        self.primal_dense = self.factor.form == "primal" and not sp.issparse(phi)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        if self.primal_dense and self.weights is None and np.ndim(y) == 1:
            # One vector (the duals' case): ``y^T Phi`` (a GEMV on C-ordered rows, faster than
            # ``Phi^T y``) and ``Lambda^{-1} = L^{-T} L^{-1}`` by two d x d products with the
            # triangular inverse, which the step forms anyway (``inverse_diagonal``).
            linv = self.factor.linv
            return linv.T @ (linv @ (np.asarray(y, dtype=float) @ self.phi))
        return self.factor.regress(y)

    def apply_pair(self, y1: np.ndarray, y2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y1), E(y2))``: for two vectors and dense unweighted primal rows, both ``y^T Phi``
        by chunks of rows that stay in cache between the two products (one pass over ``Phi``
        from memory instead of two)."""
        if not (self.primal_dense and self.weights is None and np.ndim(y1) == np.ndim(y2) == 1):
            return self(y1), self(y2)
        phi = self.phi
        f1, f2 = np.zeros(self.n_dims), np.zeros(self.n_dims)
        for s in range(0, self.n_points, _PAIR_CHUNK):
            rows = phi[s:s + _PAIR_CHUNK]
            f1 += y1[s:s + _PAIR_CHUNK] @ rows
            f2 += y2[s:s + _PAIR_CHUNK] @ rows
        linv = self.factor.linv
        return linv.T @ (linv @ f1), linv.T @ (linv @ f2)

    def pair_with_total_weights(self, y1: np.ndarray, y2: np.ndarray):
        """``(E(y1), E(y2), E(1))``: for dense unweighted primal rows one product of the
        stacked vectors (and a row of ones while ``E(1)`` is unknown) with ``Phi``, about the
        cost of one vector's (the rows are read once)."""
        if not (self.primal_dense and self.weights is None):  # one regression of both
            both = self(np.stack([y1, y2], axis=1))
            return both[:, 0].copy(), both[:, 1].copy(), self.total_weights()
        ones = self._total is None
        ys = buffer("ridge.pair", (2 + ones, self.n_points))
        ys[0], ys[1] = y1, y2
        if ones:
            ys[2] = 1.0
        sums = ys @ self.phi
        linv = self.factor.linv
        out = linv.T @ (linv @ sums.T)
        if ones:
            self._total = out[:, 2].copy()
        return out[:, 0].copy(), out[:, 1].copy(), self._total.copy()

    def total_weights(self) -> np.ndarray:
        """``E(1) = Lambda^{-1} Phi^T W 1`` (computed once per operator): for dense primal
        rows the column sums ``Phi^T W 1`` (one pass) and the ``d x d`` solve of
        :meth:`__call__`."""
        if self._total is None:
            if self.primal_dense:
                w = np.ones(self.n_points) if self.weights is None else self.weights
                self._total = self._solve_sums(w @ self.phi)
            else:
                self._total = self.factor.regress(np.ones(self.n_points))
        return self._total.copy()

    def _solve_sums(self, sums: np.ndarray) -> np.ndarray:
        """``Lambda^{-1} b`` for feature-space sums ``b (d,)``, as :meth:`__call__` applies
        ``Lambda^{-1}`` (two products with ``L^{-1}`` in the primal form)."""
        if self.factor.form == "primal" and self.factor.cols is None:
            linv = self.factor.linv
            return linv.T @ (linv @ sums)
        return self.factor.solve(sums)

    @property
    def chol_inverse(self) -> np.ndarray:
        """``L^{-1}`` (d x d, computed once; primal form): applies ``Lambda^{-1} = L^{-T}
        L^{-1}`` to many columns as two GEMMs; ``Lambda^{-1}`` itself is never formed."""
        if self.factor.form != "primal":
            raise AttributeError("chol_inverse exists for the primal form only")
        return self.factor.linv

    def weight_factors(self):
        """``(W Phi, Lambda^{-1})`` for dense rows in the primal form; else None (the dual form
        and sparse rows give the weight matrix itself, :attr:`matrix`)."""
        if not self.primal_dense:
            return None
        psi = self.phi if self.weights is None else self.phi * self.weights[:, None]
        linv = self.chol_inverse
        return psi, linv.T @ linv

    def rows(self, dims=None) -> np.ndarray:
        if dims is None:
            return self.factor.matrix()
        dims = np.atleast_1d(dims)
        if not self.primal_dense:
            return self.matrix[dims]
        xw = self.phi if self.weights is None else self.phi * self.weights[:, None]
        # Row i of Lambda^{-1} Phi^T W is (Lambda^{-1} e_i)^T Phi^T W.
        unit = np.zeros((self.n_dims, dims.size))
        unit[dims, np.arange(dims.size)] = 1.0
        return self.factor._primal_solve(unit).T @ xw.T

    def weight_columns(self, src: np.ndarray, out: np.ndarray) -> np.ndarray:
        if not self.primal_dense:
            return super().weight_columns(src, out)
        # Gather feature rows (cheap, contiguous) and apply L^{-T} L^{-1} by two GEMMs.
        xw = np.take(self.phi, np.maximum(src, 0), axis=0, mode="clip",
                     out=buffer("ridge.xw", (src.size, self.n_dims)))
        if self.weights is not None:
            xw *= self.weights[np.maximum(src, 0), None]
        missing = src < 0
        if missing.any():
            xw[missing] = 0.0
        linv = self.chol_inverse
        half = np.matmul(linv, xw.T, out=buffer("ridge.half", out.shape))
        return np.matmul(linv.T, half, out=out)

    def _sorted_features(self, v, breakpoints_extra):
        """Sorted breakpoints and the matching (weighted) feature rows, zero for extras/padding."""
        alphas, src, m = sort_breakpoints(v, breakpoints_extra)
        # mode="clip" maps the -1 of extra points and padding to row 0 (zeroed below) and,
        # unlike the default, writes straight into the buffer.
        xs = np.take(self.phi, src, axis=0, mode="clip",
                     out=buffer("ridge.xs", (src.size, self.n_dims)))
        if self.weights is not None:
            xs *= np.take(self.weights, src, mode="clip")[:, None]
        if m < src.size or len(breakpoints_extra):  # else every src is a point of v
            xs[src < 0] = 0.0
        return alphas, xs, m

    def sorted_blocks(self, v: np.ndarray, breakpoints_extra=(), moments: int = 3,
                      group: int = 1) -> SortedBlocks:
        if not self.primal_dense:
            return super().sorted_blocks(v, breakpoints_extra, moments, group)
        # in feature space: the block sums of the sorted rows, mapped by Lambda^{-1}
        alphas, xs, m = self._sorted_features(v, breakpoints_extra)
        linv = self.chol_inverse
        if self.nonnegative_features is None:
            self.nonnegative_features = bool((self.phi >= 0).all())
        nonneg = self.nonnegative_features and self.weights is None
        return blocks_from_features(alphas, xs, m, linv.T @ linv, nonneg, moments, group)

    def inverse_diagonal(self) -> np.ndarray:
        """``diag(Lambda^{-1})`` without forming the inverse (see :class:`GramFactor`)."""
        return self.factor.inverse_diagonal()


class FactorExpectation(ExpectationOperator):
    """Exact expectations under known factor distributions: ``E(y) = mu @ y``.

    Parameters
    ----------
    mu : ndarray (d, S)
        Row i is the factor distribution ``mu_{h,i}`` over the S states.

    Examples
    --------
    >>> import numpy as np
    >>> E = FactorExpectation(np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 1.0]]))
    >>> E(np.array([1.0, 3.0, 7.0]))
    array([2., 7.])
    """

    nonnegative = True

    def __init__(self, mu: np.ndarray):
        mu = np.asarray(mu, dtype=float)
        if mu.ndim != 2:
            raise ValueError(f"mu must have shape (d, S), got {mu.shape}")
        if (mu < -1e-12).any() or not np.allclose(mu.sum(axis=1), 1.0, atol=1e-9):
            raise ValueError("each row of mu must be a probability distribution over states")
        self.mu = mu
        self.n_dims, self.n_points = mu.shape

    def __call__(self, y: np.ndarray) -> np.ndarray:
        return self.mu @ y

    def rows(self, dims=None) -> np.ndarray:
        return self.mu if dims is None else self.mu[np.atleast_1d(dims)]

    def weight_factors(self):
        """``(mu^T, I)``."""
        return self.mu.T, np.eye(self.n_dims)
