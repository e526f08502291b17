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

from ._scratch import buffer

__all__ = [
    "ExpectationOperator",
    "RidgeExpectation",
    "FactorExpectation",
    "cholesky_gram",
    "cholesky_solve",
    "prefix_sums",
    "sort_breakpoints",
    "BLOCK",
]

# NumPy's LAPACK only: NumPy and SciPy wheels bundle separate OpenBLAS builds whose thread
# pools spin against each other when calls alternate (measured: 12 ms instead of 0.4 ms per
# 10,000 x 30 Gram matrix on 2 cores). d is small, so generic solves on the triangular
# factors cost nothing next to forming the Gram matrix.


def cholesky_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``Lambda x = b`` given the lower Cholesky factor ``L`` of ``Lambda = L L^T``."""
    return np.linalg.solve(chol.T, np.linalg.solve(chol, b))


class ExpectationOperator:
    """Base class: ``E(y) = M @ y`` for a (d, n) weight matrix ``M``.

    Subclasses provide :meth:`__call__` (cheap, for closed-form duals), :meth:`rows`
    (explicit weights, for the piecewise duals that need cumulative sums over sorted
    values) and ``nonnegative`` (True when every row is a probability distribution).
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

    @property
    def matrix(self) -> np.ndarray:
        """The full (d, n) weight matrix (computed once, then cached)."""
        cached = getattr(self, "_matrix_cache", None)
        if cached is None:
            cached = self.rows()
            self._matrix_cache = cached
        return cached

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

    def sorted_blocks(self, v: np.ndarray, breakpoints_extra=(), moments: int = 3
                      ) -> SortedBlocks:
        """Block sums of the sorted weight columns, for branch and bound over breakpoints.

        Returns :class:`SortedBlocks` with ``alphas (p,)`` as in :meth:`sorted_weights` and,
        for every block of 16 consecutive sorted points, the sums of ``M``, ``M v`` and (with
        ``moments=3``) ``M v^2``, and an upper bound on the sum of ``|M|`` (each ``(d, p/16)``),
        plus a function giving the exact weight columns of chosen blocks.
        """
        alphas, weights, m = self.sorted_weights(v, breakpoints_extra)
        d, p = weights.shape
        w3 = weights.reshape(d, p // BLOCK, BLOCK)
        powers = _block_powers(alphas, moments)  # (nb, moments, 16): 1, alpha, alpha^2
        sums = np.einsum("dbk,bjk->jdb", w3, powers)
        sabs = np.abs(w3).sum(axis=2)
        s2 = sums[2] if moments == 3 else None
        return SortedBlocks(alphas, m, sums[0], sums[1], s2, sabs, lambda blk: w3[:, blk])

    def truncation_cumulants(self, v: np.ndarray, breakpoints_extra=()) -> TruncationCumulants:
        """Expectations of the truncated values ``[V]_alpha = min(V, alpha)`` for every alpha.

        Sorting ``v`` once, on segment k (``alpha`` between the k-th and (k+1)-th smallest
        breakpoint) ``E([V]_alpha) = A_k + B_k alpha`` and ``E([V]_alpha^2) = C_k + B_k alpha^2``
        with prefix sums ``A``, ``C`` and tail sums ``B`` of the weights: every breakpoint of a
        piecewise dual in O(n d) after one sort. ``breakpoints_extra`` adds alphas (with zero
        weight) that must separate segments. The arrays live in reused work buffers: they are
        valid until the next call in the same thread.
        """
        d = self.n_dims
        v = np.asarray(v, dtype=float)
        m_all = v.size + len(breakpoints_extra)
        padded = -(-m_all // BLOCK) * BLOCK
        # M, M v and M v^2 (columns in sorted order) share one buffer, so that one blocked
        # prefix sum (a GEMM, about twice as fast as np.cumsum here) serves all three.
        stacked = buffer("cumulants.stacked", (3, d, padded))
        alphas, weights, m = self.sorted_weights(v, breakpoints_extra)
        stacked[0] = weights
        np.multiply(stacked[0], alphas, out=stacked[1])
        np.multiply(stacked[1], alphas, out=stacked[2])
        sums = prefix_sums(stacked.reshape(3 * d, padded)).reshape(3, d, padded)
        head, a, c = sums[0, :, :m], sums[1, :, :m], sums[2, :, :m]
        b = np.subtract(head[:, -1:], head, out=head)
        return TruncationCumulants(alphas[:m], a, b, c)


BLOCK = 16


def prefix_sums(x: np.ndarray) -> np.ndarray:
    """Cumulative sums along the last axis of a C-contiguous ``x (r, n)``, n a multiple of 16,
    into a reused buffer: per-block sums by a GEMM with a triangular matrix of ones, then
    block offsets (NumPy's ``cumsum`` is sequential; this is about twice as fast here).
    """
    r, n = x.shape
    blocks = x.reshape(r, n // BLOCK, BLOCK)
    inner = np.matmul(
        x.reshape(-1, BLOCK), _UPPER_ONES, out=buffer("prefix.inner", (r * n // BLOCK, BLOCK))
    ).reshape(blocks.shape)
    offsets = np.cumsum(inner[:, :, -1], axis=1)
    inner[:, 1:, :] += offsets[:, :-1, None]
    return inner.reshape(r, n)


_UPPER_ONES = np.triu(np.ones((BLOCK, BLOCK)))


def sort_breakpoints(v, extra=()) -> tuple[np.ndarray, np.ndarray, int]:
    """Sort ``v`` plus ``extra`` breakpoints once: ``(alphas, src, m)``.

    ``alphas`` is increasing and padded to a multiple of ``BLOCK`` by repeating the largest;
    ``src[k]`` is the index in ``v`` of the point at ``alphas[k]``, or -1 for an extra
    breakpoint or padding (zero weight); ``m`` counts the real and extra breakpoints.
    """
    v = np.asarray(v, dtype=float)
    n = v.size
    if len(extra):
        v = np.concatenate([v, np.asarray(extra, dtype=float)])
    order = np.argsort(v)
    m = order.size
    padded = -(-m // BLOCK) * BLOCK
    alphas = np.empty(padded)
    alphas[:m] = v[order]
    alphas[m:] = alphas[m - 1]
    src = np.full(padded, -1)
    src[:m] = np.where(order < n, order, -1)
    return alphas, src, m


def _block_powers(alphas: np.ndarray, moments: int = 3) -> np.ndarray:
    """``(nb, moments, 16)``: 1, alpha (and alpha^2) of every sorted point, by block."""
    a3 = alphas.reshape(-1, BLOCK)
    rows = [np.ones_like(a3), a3, a3 * a3][:moments]
    return np.stack(rows, axis=1)


class SortedBlocks:
    """Sorted breakpoints and per-block weight sums (see :meth:`ExpectationOperator.sorted_blocks`).

    Attributes: ``alphas (p,)``, ``m`` (real breakpoints), ``s0, s1, s2 (d, nb)`` the block sums
    of ``M``, ``M v``, ``M v^2``, ``sabs (d, nb)`` an upper bound on the block sums of ``|M|``,
    and ``columns(blocks) -> (d, len(blocks), 16)`` the exact weights of chosen blocks.
    """

    __slots__ = ("alphas", "m", "s0", "s1", "s2", "sabs", "columns")

    def __init__(self, alphas, m, s0, s1, s2, sabs, columns):
        self.alphas, self.m, self.s0, self.s1, self.s2 = alphas, m, s0, s1, s2
        self.sabs, self.columns = sabs, columns


class TruncationCumulants:
    """Sorted breakpoints ``alphas (n,)`` and segment coefficients ``A, B, C (d, n)``.

    At ``alpha`` in ``[alphas[k], alphas[k+1]]`` (and at ``alphas[k]`` itself):
    ``E([V]_alpha) = A[:, k] + B[:, k] alpha`` and ``E([V]_alpha^2) = C[:, k] + B[:, k] alpha^2``.
    """

    __slots__ = ("alphas", "a", "b", "c")

    def __init__(self, alphas, a, b, c):
        self.alphas, self.a, self.b, self.c = alphas, a, b, c


def cholesky_gram(phi: np.ndarray, gamma: float, weights: np.ndarray | None = None) -> np.ndarray:
    """Lower Cholesky factor of ``Lambda = sum_tau w_tau phi_tau phi_tau^T + gamma I``.

    The Gram matrix of Algorithms 1-2 (line 3), optionally weighted by ``w = 1/sigma^2``
    for the variance-aware variants.
    """
    xw = phi if weights is None else phi * weights[:, None]
    gram = xw.T @ phi
    gram[np.diag_indices_from(gram)] += gamma
    try:
        return np.linalg.cholesky(gram)
    except np.linalg.LinAlgError:
        raise GramMatrixError(
            f"the Gram matrix Lambda = Phi^T Phi + gamma I is not numerically positive "
            f"definite: gamma = {gamma!r} is too small for these collinear (rank-deficient) "
            "features; use a larger gamma (the default is 1.0)"
        ) from None


class GramMatrixError(np.linalg.LinAlgError):
    """The ridge Gram matrix has no Cholesky factor: gamma is too small for the features.

    A ``LinAlgError``, hence a ``ValueError``."""


class RidgeExpectation(ExpectationOperator):
    """Ridge-regression estimate of the factor expectations: ``E(y) = Lambda^{-1} Phi^T W y``.

    Parameters
    ----------
    phi : ndarray (n, d)
        Features of the taken actions at this step.
    chol : ndarray (d, d)
        Lower Cholesky factor of ``Lambda = Phi^T W Phi + gamma I`` (see :func:`cholesky_gram`).
    weights : ndarray (n,), optional
        Sample weights ``w = 1 / sigma^2`` (variance-aware regression); None means 1.

    Examples
    --------
    >>> import numpy as np
    >>> phi = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    >>> E = RidgeExpectation(phi, cholesky_gram(phi, gamma=1e-12))
    >>> np.round(E(np.array([1.0, 5.0, 3.0])), 6)      # per-factor sample means
    array([2., 5.])
    """

    nonnegative = False

    def __init__(self, phi: np.ndarray, chol: np.ndarray, weights: np.ndarray | None = None,
                 nonnegative_features: bool | None = None):
        self.phi = phi
        self.chol = chol
        self.weights = weights
        self.nonnegative_features = nonnegative_features  # phi >= 0 (None: check when needed)
        self.n_points, self.n_dims = phi.shape

    def __call__(self, y: np.ndarray) -> np.ndarray:
        yw = y if self.weights is None else (y.T * self.weights).T
        return cholesky_solve(self.chol, self.phi.T @ yw)

    @property
    def chol_inverse(self) -> np.ndarray:
        """``L^{-1}`` (d x d, computed once): applies ``Lambda^{-1} = L^{-T} L^{-1}`` to many
        columns as two GEMMs; ``Lambda^{-1}`` itself is never formed."""
        linv = getattr(self, "_linv", None)
        if linv is None:
            linv = self._linv = np.linalg.solve(self.chol, np.eye(self.n_dims))
        return linv

    def weight_columns(self, src: np.ndarray, out: np.ndarray) -> np.ndarray:
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
        missing = src < 0
        if missing.any():
            xs[missing] = 0.0
        return alphas, xs, m

    def sorted_blocks(self, v: np.ndarray, breakpoints_extra=(), moments: int = 3
                      ) -> SortedBlocks:
        # M = Lambda^{-1} X^T is linear in the features: sum each block in feature space
        # (one batched product), then map the (nb, d) sums by Lambda^{-1}. |M| is bounded by
        # |Lambda^{-1}| |X|; exact columns are formed only for the blocks asked for.
        alphas, xs, m = self._sorted_features(v, breakpoints_extra)
        d = self.n_dims
        x3 = xs.reshape(-1, BLOCK, d)
        fsum = np.matmul(_block_powers(alphas, moments), x3)  # (nb, moments, d)
        linv = self.chol_inverse
        nb = fsum.shape[0]
        # (nb * moments, d) @ Lambda^{-1} as one GEMM (it is symmetric), then (moments, d, nb).
        sums = (fsum.reshape(-1, d) @ (linv.T @ linv)).reshape(nb, moments, d).transpose(1, 2, 0)
        if self.nonnegative_features is None:
            self.nonnegative_features = bool((self.phi >= 0).all())
        nonneg = self.nonnegative_features and self.weights is None
        fabs = fsum[:, 0] if nonneg else np.abs(x3).sum(axis=1)
        sabs = np.abs(linv.T @ linv) @ fabs.T

        def columns(blocks):
            cols = x3[blocks].reshape(-1, d)  # (len * 16, d)
            return (linv.T @ (linv @ cols.T)).reshape(d, len(blocks), BLOCK)

        s2 = sums[2] if moments == 3 else None
        return SortedBlocks(alphas, m, sums[0], sums[1], s2, sabs, columns)

    def rows(self, dims=None) -> np.ndarray:
        xw = self.phi if self.weights is None else self.phi * self.weights[:, None]
        if dims is None:
            linv = self.chol_inverse
            return linv.T @ (linv @ xw.T)
        dims = np.atleast_1d(dims)
        # Row i of Lambda^{-1} Phi^T W is (Lambda^{-1} e_i)^T Phi^T W.
        unit = np.zeros((self.n_dims, dims.size))
        unit[dims, np.arange(dims.size)] = 1.0
        return cholesky_solve(self.chol, unit).T @ xw.T

    def inverse_diagonal(self) -> np.ndarray:
        """``diag(Lambda^{-1})`` without forming the inverse: column norms of ``L^{-1}``."""
        linv = self.chol_inverse
        return np.einsum("ij,ij->j", linv, linv)


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
