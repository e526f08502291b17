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

import copy

import numpy as np
import scipy.sparse as sp

from ._scratch import buffer

__all__ = [
    "ExpectationOperator",
    "RidgeExpectation",
    "FactorExpectation",
    "GramFactor",
    "choose_form",
    "cholesky_gram",
    "cholesky_solve",
    "prefix_sums",
    "sort_breakpoints",
    "sort_order",
    "group_sums",
    "fine_blocks",
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

    def apply_pair(self, y1: np.ndarray, y2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y1), E(y2))`` for two vectors ``(n,)`` (subclasses may share one pass)."""
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

        Returns :class:`SortedBlocks` with ``alphas (p,)`` as in :meth:`sorted_weights` and,
        for every block of ``16 group`` consecutive sorted points (the last one may be
        shorter), the sums of ``M``, ``M v`` and (with ``moments=3``) ``M v^2``, and an upper
        bound on the sum of ``|M|`` (each ``(d, ceil(p / (16 group)))``), plus functions giving
        the same sums on the blocks of 16 inside chosen (factor, block) pairs and the exact
        weights of chosen (factor, block of 16) pairs. The arrays may live in reused work
        buffers: valid until the next call in the same thread.
        """
        alphas, weights, m = self.sorted_weights(v, breakpoints_extra)
        d, p = weights.shape
        w3 = weights.reshape(d, p // BLOCK, BLOCK)
        powers = _block_powers(alphas, moments)  # (nb, moments, 16): 1, alpha, alpha^2
        sums = np.einsum("dbk,bjk->jdb", w3, powers)  # (moments, d, nb)
        sabs = np.abs(w3).sum(axis=2)

        def fine_sums(rows, blocks):
            r, idx = rows[:, None], fine_blocks(blocks, group, w3.shape[1])
            return sums[:, r, idx], sabs[r, idx]

        return SortedBlocks(alphas, m, group, group_sums(sums, group, axis=2),
                            group_sums(sabs, group, axis=1), fine_sums,
                            lambda rows, blk: w3[rows, blk])

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
# Rows per chunk of RidgeExpectation.apply_pair: 1024 x 30 float64 = 240 kB, within L2.
_PAIR_CHUNK = 1024


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


def sort_order(v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """An ``order`` with ``v[order]`` non-decreasing (a permutation, like ``np.argsort(v)``;
    equal values in index order, except that every -0.0 comes before every 0.0), and
    ``v[order]`` written into ``out`` if given.

    One ``np.sort`` of 64-bit keys instead of ``np.argsort`` (about 2x faster from 1e4 values
    on): the bits of each float made order-preserving as integers, their last ``b`` bits
    replaced by the index (``2^b >= n``). Values that differ in those bits only come out in
    index order: each such run is then sorted by value (few and short). With NaN it is
    ``np.argsort`` (NaN keys come first or last, or share the run of an infinity when the
    NaN's payload lies in the last ``b`` bits: checked whenever an infinity ends the sort).
    """
    v = np.ascontiguousarray(v, dtype=float)
    n = v.size
    shift = int(n - 1).bit_length()
    if n < 2 or shift > 40:
        order = np.argsort(v)
        if out is not None:
            np.take(v, order, out=out)
        return order
    bits = v.view(np.int64)
    keys = bits >> 63  # -1 for a set sign bit: flip the other bits of negative floats
    keys &= np.int64(0x7FFFFFFFFFFFFFFF)
    keys ^= bits  # now increasing as signed integers where the floats increase
    keys &= np.int64(-1 << shift)
    keys |= np.arange(n)
    keys.sort()
    order = keys & np.int64((1 << shift) - 1)
    s = np.take(v, order, out=out)
    if np.isnan(s[0]) or np.isnan(s[-1]) or (
            (s[0] == -np.inf or s[-1] == np.inf) and np.isnan(s).any()):  # np.argsort's order
        order = np.argsort(v)
        np.take(v, order, out=s)
        return order
    wrong = np.flatnonzero(s[1:] < s[:-1])
    if wrong.size:  # runs of values equal but for their last bits: sort each by value
        run_key = keys >> shift
        bad = np.unique(run_key[wrong])
        lo = np.searchsorted(run_key, bad, "left")
        size = np.searchsorted(run_key, bad, "right") - lo
        pos = np.repeat(lo - np.cumsum(size) + size, size) + np.arange(size.sum())
        by_value = pos[np.lexsort((s[pos], run_key[pos]))]
        order[pos] = order[by_value]
        s[pos] = s[by_value]
    return order


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
    m = v.size
    padded = -(-m // BLOCK) * BLOCK
    alphas = np.empty(padded)
    order = sort_order(v, out=alphas[:m])
    alphas[m:] = alphas[m - 1]
    if m == n and padded == m:  # no extra breakpoints, no padding: the order itself
        return alphas, order, m
    src = np.full(padded, -1)
    src[:m] = np.where(order < n, order, -1)
    return alphas, src, m


def _block_powers(alphas: np.ndarray, moments: int = 3) -> np.ndarray:
    """``(nb, moments, 16)``: 1, alpha (and alpha^2) of every sorted point, by block."""
    a3 = alphas.reshape(-1, BLOCK)
    out = buffer("blocks.powers", (a3.shape[0], moments, BLOCK))
    out[:, 0] = 1.0
    out[:, 1] = a3
    if moments > 2:
        np.multiply(a3, a3, out=out[:, 2])
    return out


class SortedBlocks:
    """Sorted breakpoints and per-block weight sums (see :meth:`ExpectationOperator.sorted_blocks`).

    Attributes: ``alphas (p,)``, ``m`` (real breakpoints), ``group`` (blocks of 16 per block of
    the first level), ``sums (moments, d, nc)``: the sums ``s0, s1`` (and ``s2``) of ``M``,
    ``M v`` (and ``M v^2``) over the blocks of ``16 group`` sorted points, ``sabs (d, nc)`` an
    upper bound on their sums of ``|M|``; ``fine(rows, blocks)``, the same ``(sums (moments, P,
    group), sabs (P, group))`` of factor ``rows[p]`` on the blocks of 16 inside block
    ``blocks[p]`` (of ``16 group``; past the end: the last block of 16, see
    :func:`fine_blocks`); and ``pairs(rows, blocks) -> (P, 16)`` the exact weights of factor
    ``rows[p]`` on block of 16 ``blocks[p]``.
    """

    __slots__ = ("alphas", "m", "group", "sums", "sabs", "fine", "pairs")

    def __init__(self, alphas, m, group, sums, sabs, fine, pairs):
        self.alphas, self.m, self.group = alphas, m, group
        self.sums, self.sabs, self.fine, self.pairs = sums, sabs, fine, pairs

    s0 = property(lambda self: self.sums[0])
    s1 = property(lambda self: self.sums[1])
    s2 = property(lambda self: self.sums[2] if len(self.sums) > 2 else None)


def fine_blocks(blocks: np.ndarray, group: int, n_blocks: int) -> np.ndarray:
    """``(P, group)``: the blocks of 16 inside the blocks ``blocks (P,)`` of ``16 group``, the
    indices past the last block of 16 (``n_blocks - 1``) clamped to it."""
    return np.minimum(blocks[:, None] * group + np.arange(group), n_blocks - 1)


def group_sums(x: np.ndarray | None, group: int, axis: int = 0) -> np.ndarray | None:
    """Sums of ``x`` over consecutive groups of ``group`` entries along ``axis`` (the last
    group may be shorter; left to right, ``x[0] + x[1] + ...``)."""
    if group == 1 or x is None:
        return x
    if axis != 0:
        return np.moveaxis(group_sums(np.moveaxis(x, axis, 0), group), 0, axis)
    n = x.shape[0]
    full = n // group * group
    out = np.empty((-(-n // group),) + x.shape[1:])
    head = out[:full // group]  # strided adds: np.add.reduceat is 4x slower here
    np.add(x[0:full:group], x[1:full:group], out=head)
    for k in range(2, group):
        head += x[k:full:group]
    if full < n:
        out[-1] = x[full:].sum(axis=0)
    return out


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
    for the variance-aware variants. ``phi`` may be a ``scipy.sparse`` matrix (d x d result).
    """
    if sp.issparse(phi):
        xw = phi if weights is None else sp.diags(weights) @ phi
        gram = np.asarray((xw.T @ phi).toarray(), dtype=float)
    else:
        xw = phi if weights is None else phi * weights[:, None]
        gram = xw.T @ phi
    return ridge_cholesky(gram, gamma)


def ridge_cholesky(gram: np.ndarray, gamma: float) -> np.ndarray:
    """Lower Cholesky factor of ``gram + gamma I`` (``gram`` is modified), or a
    :class:`GramMatrixError` naming ``gamma`` when it does not exist."""
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


FORMS = ("auto", "primal", "dual")

# From this size on, triangular inverses go through LAPACK's trtri (d^3/3 flops) rather than
# a generic solve against the identity (about 8x the flops): measured at d = 1152 with one BLAS
# thread, 60 ms against 336 ms. Below it, NumPy's LAPACK only (see the note above).
_TRTRI_FROM = 256


def _triangular_inverse(lower: np.ndarray) -> np.ndarray:
    """``L^{-1}`` of a lower-triangular ``L``."""
    n = lower.shape[0]
    if n < _TRTRI_FROM:
        return np.linalg.solve(lower, np.eye(n))
    from scipy.linalg import lapack

    inv, info = lapack.dtrtri(lower, lower=1)
    if info != 0:  # pragma: no cover - a Cholesky factor has a positive diagonal
        raise np.linalg.LinAlgError(f"triangular inverse failed (info={info})")
    return np.tril(inv)


def _lower_solve(lower: np.ndarray, b: np.ndarray, trans: str = "N") -> np.ndarray:
    """``L^{-1} b`` (``trans="N"``) or ``L^{-T} b`` (``"T"``) for a lower-triangular ``L``."""
    from scipy.linalg import solve_triangular

    return solve_triangular(lower, b, lower=True, trans=trans, check_finite=False)


def _used_columns(phi) -> np.ndarray:
    """The features some sparse row stores an entry for (sorted)."""
    return np.unique(sp.csr_matrix(phi).indices)


class _UsedFeaturesFactor:
    """The elliptical factor of a sparse-row primal form: ``Lambda`` is block diagonal,
    ``Lambda_U`` on the used features ``U`` and ``gamma I`` off them, so
    ``||x||^2_{Lambda^{-1}} = ||L_U^{-1} x_U||^2 + ||x_{not U}||^2 / gamma``. :meth:`apply_rows`
    returns ``[L_U^{-1} x_U, ||x_{not U}|| / sqrt(gamma)]`` per row, whose squared norm is that."""

    def __init__(self, linv, cols, gamma):
        self.linv, self.cols, self.gamma = linv, np.asarray(cols), float(gamma)

    def apply_rows(self, x):
        xs = sp.csr_matrix(x) if sp.issparse(x) else np.asarray(x)
        used = xs[:, self.cols]
        sq_all = np.asarray(xs.multiply(xs).sum(axis=1) if sp.issparse(xs) else
                            np.einsum("ij,ij->i", xs, xs)).ravel()
        used_d = used.toarray() if sp.issparse(used) else used
        rest = np.maximum(sq_all - np.einsum("ij,ij->i", used_d, used_d), 0.0)
        return np.hstack([used_d @ self.linv.T, np.sqrt(rest / self.gamma)[:, None]])


def choose_form(n: int, d: int, sparse: bool = False) -> str:
    """Primal (d x d) or dual (n x n, Woodbury) factorization of ``Lambda``: dual when d > n.

    Counting multiply-adds, the primal costs ``n d^2 / 2`` (Gram) ``+ d^3 / 3`` (Cholesky and
    triangular inverse) and the dual ``n^2 d`` (Gram and ``C^{-1} Psi``) ``+ n^3 / 3``; the
    counts cross a little below d = n, but LAPACK's factorizations run slower than the
    Gram products: measured at n = 1000, d = 1152 (one BLAS thread, a TV step with the
    diagonal of ``Lambda^{-1}``), primal 907 ms and dual 675 ms. So the dual form whenever
    d > n. For sparse rows ``d`` is the number of *used* features (those some row stores an
    entry for): ``Lambda`` is ``gamma I`` off them, so the primal form factors a dense matrix
    of that size only (:class:`GramFactor`).
    """
    return "dual" if d > n else "primal"


class GramFactor:
    """Exact factorization of ``Lambda = Phi^T W Phi + gamma I`` in primal or dual form.

    With ``Psi = W^{1/2} Phi`` (n x d; dense or ``scipy.sparse``):

    - **primal** (``d x d``): ``Lambda = L L^T`` (Cholesky), ``L^{-1}`` by one triangular
      inverse; ``Lambda^{-1} b = L^{-T} L^{-1} b``, ``diag(Lambda^{-1})`` = column norms of
      ``L^{-1}``.
    - **dual** (``n x n``, Woodbury): ``G = Psi Psi^T + gamma I = C C^T``. Then
      ``Lambda^{-1} Psi^T = Psi^T G^{-1}`` (the push-through identity), so the ridge weights are
      ``Lambda^{-1} Phi^T W y = Psi^T G^{-1} W^{1/2} y`` with no cancellation, and
      ``Lambda^{-1} = (I - Psi^T G^{-1} Psi) / gamma`` gives ``diag(Lambda^{-1})`` and
      ``||x||^2_{Lambda^{-1}} = (||x||^2 - ||C^{-1} Psi x||^2) / gamma`` from the same factor.
      These two subtract quantities of size ``||x||^2``: relative error about
      ``eps * ||x||^2 / (gamma ||x||^2_{Lambda^{-1}})``, i.e. ``eps`` times the ratio of the
      data's coverage of ``x`` to ``gamma`` (1e-13 for counts up to 1e3 with ``gamma = 1``).
      The same holds for the weights when rows repeat (``Psi Psi^T`` singular): ``G^{-1}``
      amplifies its null space by ``1/gamma`` and ``Psi^T`` cancels it, leaving errors of about
      ``eps ||Psi||^2 / gamma``. For a tiny ``gamma`` force ``form="primal"``.

    ``form="auto"`` picks the cheaper one from the shapes (:func:`choose_form`); both give the
    same numbers to rounding.

    With sparse rows (tile coding: tens of thousands of features, a few hundred of them used at
    a step) the primal form works on the used features ``U`` only: no row of ``Phi`` has an
    entry off ``U``, so ``Lambda`` is block diagonal, ``Lambda_U = Phi_U^T W Phi_U + gamma I``
    (dense, ``|U| x |U|``, factored) and ``gamma I`` elsewhere; the weights are 0 off ``U``
    and ``diag(Lambda^{-1})`` is ``1 / gamma`` there. Exact, and it costs ``|U|^3`` instead of
    the dual's ``n^3`` when ``|U| < n``.

    Parameters
    ----------
    phi : ndarray or scipy.sparse matrix (n, d)
    gamma : float
        Ridge parameter (> 0).
    weights : ndarray (n,), optional
        Regression weights ``w >= 0`` (variance-aware variants); None means 1.
    form : {"auto", "primal", "dual"}

    Examples
    --------
    >>> import numpy as np
    >>> phi = np.random.default_rng(0).random((3, 5))          # n = 3 < d = 5: dual
    >>> f = GramFactor(phi, gamma=0.5)
    >>> f.form
    'dual'
    >>> lam = phi.T @ phi + 0.5 * np.eye(5)
    >>> bool(np.allclose(f.inverse_diagonal(), np.diag(np.linalg.inv(lam))))
    True
    """

    def __init__(self, phi, gamma: float, weights: np.ndarray | None = None, form: str = "auto"):
        if form not in FORMS:
            raise ValueError(f"form must be one of {FORMS}, got {form!r}")
        self.sparse = sp.issparse(phi)
        if self.sparse:
            phi = sp.csr_matrix(phi, dtype=float)
        self.phi = phi
        self.weights = weights
        self.gamma = float(gamma)
        self.n, self.d = phi.shape
        # Sparse rows: the primal form lives on the used features only (see the class notes).
        self.cols = _used_columns(phi) if self.sparse else None
        if form == "auto":
            form = choose_form(self.n, self.d if self.cols is None else self.cols.size)
        self.form = form
        self._linv = self._cinv = self._u = None
        if self.form == "primal":
            self.chol = cholesky_gram(self._phi_used, gamma, weights)
            return
        self.chol = None
        self.root = None if weights is None else np.sqrt(weights)
        psi = self.psi
        gram = psi @ psi.T
        gram = np.array(gram.toarray() if self.sparse else gram, dtype=float)
        gram[np.diag_indices_from(gram)] += gamma
        try:
            self.dual_chol = np.linalg.cholesky(gram)
        except np.linalg.LinAlgError:
            raise GramMatrixError(
                f"the Gram matrix Psi Psi^T + gamma I (dual form) is not numerically positive "
                f"definite: gamma = {gamma!r} is too small for these features; use a larger "
                "gamma (the default is 1.0)"
            ) from None

    @classmethod
    def from_cholesky(cls, phi, chol: np.ndarray, weights: np.ndarray | None = None,
                      gamma: float | None = None) -> GramFactor:
        """A primal factor from a given lower Cholesky factor of ``Lambda``."""
        self = cls.__new__(cls)
        self.sparse = sp.issparse(phi)
        self.phi, self.weights, self.chol = phi, weights, chol
        self.n, self.d = phi.shape
        self.gamma = gamma
        self.form = "primal"
        self.cols = None
        self._linv = self._cinv = self._u = None
        return self

    # ------------------------------------------------------------------ pieces
    @property
    def _phi_used(self):
        """The rows on the used features (all of them for dense rows; computed once)."""
        if self.cols is None:
            return self.phi
        if getattr(self, "_used_rows", None) is None:
            self._used_rows = self.phi[:, self.cols]
        return self._used_rows

    def _on_used(self, used_part, fill):
        """A ``(d, ...)`` array equal to ``fill`` off the used features and ``used_part`` on
        them (sparse-row primal form); ``used_part`` itself for dense rows."""
        if self.cols is None:
            return used_part
        out = np.full((self.d,) + used_part.shape[1:], fill, dtype=float) if np.isscalar(
            fill) else np.array(fill, dtype=float)
        out[self.cols] = used_part
        return out

    @property
    def psi(self):
        """``W^{1/2} Phi`` (n x d), the rows that enter the Gram matrix (computed once)."""
        root = getattr(self, "root", None)
        if root is None:
            return self.phi
        if getattr(self, "_psi", None) is None:
            self._psi = sp.diags(root) @ self.phi if self.sparse else self.phi * root[:, None]
        return self._psi

    @property
    def linv(self) -> np.ndarray:
        """``L^{-1}`` (primal form; computed once)."""
        if self._linv is None:
            self._linv = _triangular_inverse(self.chol)
        return self._linv

    @property
    def cinv(self) -> np.ndarray:
        """``C^{-1}`` with ``C C^T = Psi Psi^T + gamma I`` (dual form; computed once)."""
        if self._cinv is None:
            self._cinv = _triangular_inverse(self.dual_chol)
        return self._cinv

    @property
    def u(self) -> np.ndarray:
        """``U = C^{-1} Psi`` (n x d, dense; dual form; computed once): one triangular solve
        (``n^2 d / 2`` multiply-adds, half a GEMM) for dense features."""
        if self._u is None:
            psi = self.psi
            if self.sparse:
                self._u = np.asarray((psi.T @ self.cinv.T).T)
            else:
                self._u = _lower_solve(self.dual_chol, psi)
        return self._u

    @property
    def z(self) -> np.ndarray:
        """``Z = G^{-1} Psi`` (n x d, dense features, dual form; computed once): one GEMM gives
        both the weight matrix ``M = Z^T W^{1/2}`` and ``diag(Psi^T G^{-1} Psi)``."""
        if getattr(self, "_z", None) is None:
            if self.sparse:
                self._z = self.ginv @ self.psi
            else:  # C^-T U: one triangular solve (n^2 d / 2), no n x n inverse
                self._z = _lower_solve(self.dual_chol, self.u, trans="T")
        return self._z

    @property
    def ginv(self) -> np.ndarray:
        """``G^{-1} = C^{-T} C^{-1}`` (n x n; dual form; computed once)."""
        if getattr(self, "_ginv", None) is None:
            self._ginv = self.cinv.T @ self.cinv
        return self._ginv

    def _primal_solve(self, b):
        """``Lambda^{-1} b = L^{-T} L^{-1} b``. Small d: two generic solves on ``L`` (an LU
        each, nothing kept). From ``_TRTRI_FROM`` on, a generic solve costs ``O(d^3)`` per
        call, so the triangular inverse is formed once (``d^3 / 3``) and every solve is two
        products: measured at d = 1152 (one BLAS thread) 2.6 ms against 94 ms per solve."""
        if self.chol.shape[0] < _TRTRI_FROM:
            return cholesky_solve(self.chol, b)
        linv = self.linv
        return linv.T @ (linv @ b)

    def _dual_apply(self, z):
        """``G^{-1} z = C^{-T} C^{-1} z`` for ``z (n,)`` or ``(n, m)``."""
        ci = self.cinv
        return ci.T @ (ci @ z)

    def active_features(self) -> np.ndarray | None:
        """Indices of the features some row uses (sparse rows), None for dense rows."""
        if not self.sparse:
            return None
        return self.cols  # found once, when the factor was formed

    def restrict(self, cols: np.ndarray) -> GramFactor:
        """The factor of the features ``cols`` alone, for a dual-form factor whose other
        features are unused (zero columns): ``Lambda`` is then block diagonal, ``Psi Psi^T``
        and its factor are unchanged and shared."""
        if self.form != "dual" and self.cols is None:
            raise ValueError("restrict needs the dual form or sparse rows")
        new = copy.copy(self)
        new._used_rows = None
        new.phi, new.d = self.phi[:, cols], len(cols)
        if self.cols is not None:  # the used features, renumbered (they keep their order)
            where = np.full(self.d, -1)
            where[np.asarray(cols)] = np.arange(len(cols))
            pos = where[self.cols]
            if np.any(pos < 0) or np.any(np.diff(pos) <= 0):
                raise ValueError("restrict: cols must hold every used feature, in order")
            new.cols = pos
        if self.form == "primal":  # the used features keep their factor
            return new
        new._psi = None
        new._u = None if self._u is None else self._u[:, cols]
        new._z = None if getattr(self, "_z", None) is None else self._z[:, cols]
        return new

    # ------------------------------------------------------------------ the operator
    def regress(self, y: np.ndarray) -> np.ndarray:
        """Ridge weights ``Lambda^{-1} Phi^T W y`` for ``y (n,)`` or ``(n, m)``."""
        if self.form == "primal":
            yw = y if self.weights is None else (y.T * self.weights).T
            w = self._primal_solve(np.asarray(self._phi_used.T @ yw))
            return self._on_used(w, 0.0)  # unused features: Phi^T y = 0 there
        ys = y if self.root is None else (y.T * self.root).T
        if not self.sparse:  # Psi^T G^-1 = U^T C^-1 with U (needed for the diagonal anyway)
            return self.u.T @ _lower_solve(self.dual_chol, ys)
        return np.asarray(self.psi.T @ self._dual_apply(ys))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``Lambda^{-1} b`` for ``b (d,)`` or ``(d, m)``."""
        if self.form == "primal":
            if self.cols is None:
                return self._primal_solve(b)
            return self._on_used(self._primal_solve(b[self.cols]), b / self.gamma)
        if not self.sparse:
            u = self.u
            return (b - u.T @ (u @ b)) / self.gamma
        psi = self.psi
        return (b - np.asarray(psi.T @ self._dual_apply(np.asarray(psi @ b)))) / self.gamma

    def matrix(self) -> np.ndarray:
        """The weight matrix ``M = Lambda^{-1} Phi^T W`` (d x n, dense)."""
        if self.form == "primal":
            phi = self._phi_used
            xw = phi if self.weights is None else _scale_rows(phi, self.weights)
            if self.sparse:  # Lambda_U^{-1} (|U|^3) times sparse rows: nnz |U|, not |U|^2 n
                linv = self.linv
                return self._on_used(np.asarray(xw @ (linv.T @ linv)).T, 0.0)
            return self.linv.T @ (self.linv @ xw.T)
        if not self.sparse:
            m = np.array(self.z.T, order="C")  # a copy: z stays cached
            return m if self.root is None else np.multiply(m, self.root, out=m)
        g = self.ginv if self.root is None else self.ginv * self.root
        return np.asarray(self.psi.T @ g)

    def inverse_diagonal(self) -> np.ndarray:
        """``diag(Lambda^{-1})`` without forming ``Lambda^{-1}``."""
        if self.form == "primal":
            linv = self.linv
            return self._on_used(np.einsum("ij,ij->j", linv, linv), 1.0 / self.gamma)
        if self.sparse:
            quad = _sparse_column_quadratic(self.psi, self.ginv)
        elif getattr(self, "_z", None) is not None:  # the weight matrix was formed: n d more
            quad = np.einsum("ij,ij->j", self.psi, self._z)
        else:
            u = self.u
            quad = np.einsum("ij,ij->j", u, u)
        return np.clip(1.0 - quad, 0.0, 1.0) / self.gamma

    def elliptical_factor(self):
        """``(R, c0, c1)`` with ``||x||^2_{Lambda^{-1}} = c0 ||x||^2 + c1 ||R x||^2``.

        Primal: ``(L^{-1}, 0, 1)``; dual: ``(C^{-1} Psi, 1/gamma, -1/gamma)``. Acting needs only
        these products: computed once by ``fit``, never a factorization per call.
        """
        if self.form == "primal":
            if self.cols is None:
                return self.linv, 0.0, 1.0
            return _UsedFeaturesFactor(self.linv, self.cols, self.gamma), 0.0, 1.0
        r = self.u if not self.sparse else _SparseProduct(self.cinv, self.psi)
        return r, 1.0 / self.gamma, -1.0 / self.gamma


def _scale_rows(x, w):
    return sp.diags(w) @ x if sp.issparse(x) else x * w[:, None]


class _SparseProduct:
    """``R = C^{-1} Psi`` kept as its two factors (``Psi`` sparse): ``R @ x^T`` without
    forming the dense n x d matrix."""

    def __init__(self, cinv, psi):
        self.cinv, self.psi = cinv, sp.csr_matrix(psi)
        self.shape = (cinv.shape[0], psi.shape[1])

    def apply_rows(self, x):
        """``(R x_j)_j`` for rows ``x (m, d)``: ``(m, n)``."""
        return np.asarray((self.psi @ x.T).T @ self.cinv.T) if not sp.issparse(x) else \
            np.asarray((x @ self.psi.T).toarray() @ self.cinv.T)


def _sparse_column_quadratic(psi, ginv: np.ndarray) -> np.ndarray:
    """``diag(Psi^T G^{-1} Psi)`` for sparse ``Psi (n, d)``, on the used columns only:
    ``Z = Psi_A^T G^{-1}`` (``nnz(Psi) n`` flops, ``|A| x n`` dense for the ``|A|`` used
    columns), then the sum of ``Psi_A^T * Z`` over the non-zeros; unused columns give 0."""
    csc = sp.csc_matrix(psi)
    out = np.zeros(csc.shape[1])
    used = np.flatnonzero(np.diff(csc.indptr))
    if used.size == 0:
        return out
    sub_t = csc[:, used].T.tocsr()  # (|A|, n)
    z = np.asarray(sub_t @ ginv)
    out[used] = np.asarray(sub_t.multiply(z).sum(axis=1)).ravel()
    return out


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
        self.phi = phi
        if isinstance(chol, GramFactor):
            self.factor = chol
        else:
            self.factor = GramFactor.from_cholesky(phi, chol, weights)
        self.chol = self.factor.chol
        self.weights = weights
        self.nonnegative_features = nonnegative_features  # phi >= 0 (None: check when needed)
        self.n_points, self.n_dims = phi.shape
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
        """``(E(y1), E(y2))``: for dense primal rows, both ``y^T Phi`` by chunks of rows that
        stay in cache between the two products (one pass over ``Phi`` from memory instead of
        two; measured 0.31 ms against 0.54 ms at n = 10,000, d = 30 from a cold cache)."""
        if not (self.primal_dense and self.weights is None):
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
        ones = getattr(self, "_total", None) is None
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
        if getattr(self, "_total", None) is None:
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
        # M = Lambda^{-1} X^T is linear in the features: sum each block of 16 in feature space
        # (one batched product), add those up by groups, and map only the groups' (nc, d)
        # sums by Lambda^{-1}; the sums of blocks of 16 are mapped on demand, for the
        # (factor, block) pairs a scan refines. |M| is bounded by |Lambda^{-1}| |X|; exact
        # weights are formed only for the pairs asked for: row i of Lambda^{-1} times the
        # block's 16 feature rows.
        alphas, xs, m = self._sorted_features(v, breakpoints_extra)
        d = self.n_dims
        x3 = xs.reshape(-1, BLOCK, d)
        nb = x3.shape[0]
        fsum = np.matmul(_block_powers(alphas, moments), x3,
                         out=buffer("ridge.fsum", (nb, moments, d)))  # (nb, moments, d)
        linv = self.chol_inverse
        gram_inv = linv.T @ linv  # Lambda^{-1} (d x d)
        csum = group_sums(fsum, group)
        # (moments, d, nc) C-ordered, so that the per-factor running sums over blocks read
        # rows: Lambda^{-1} times the transposed sums, straight into a work buffer (BLAS reads
        # the transposed operand; measured 4x faster than (nc * moments, d) @ Lambda^{-1}
        # followed by a transposing copy).
        sums = np.matmul(gram_inv, csum.transpose(1, 2, 0),
                         out=buffer("ridge.sums", (moments, d, csum.shape[0])))
        if self.nonnegative_features is None:
            self.nonnegative_features = bool((self.phi >= 0).all())
        nonneg = self.nonnegative_features and self.weights is None
        fabs = fsum[:, 0] if nonneg else np.abs(x3).sum(axis=1)  # (nb, d)
        abs_inv = np.abs(gram_inv)
        sabs = abs_inv @ (csum[:, 0] if nonneg else group_sums(fabs, group)).T

        def fine(rows, blocks):
            # Lambda^{-1} (and |Lambda^{-1}|) on the feature sums of the distinct blocks asked
            # for only (U of them; a mask and its running count instead of np.unique's sort).
            seen = np.zeros(csum.shape[0], dtype=bool)
            seen[blocks] = True
            ub = np.flatnonzero(seen)
            inv = (np.cumsum(seen) - 1)[blocks]
            idx = fine_blocks(ub, group, nb).ravel()  # (U group,)
            mapped = np.empty((moments + 1, d, idx.size))
            np.matmul(gram_inv, fsum[idx].transpose(1, 2, 0), out=mapped[:moments])
            np.matmul(abs_inv, fabs[idx].T, out=mapped[moments])
            out = mapped.reshape(moments + 1, d, ub.size, group)[
                :, rows[:, None], inv[:, None], np.arange(group)]  # (moments + 1, P, group)
            return out[:moments], out[moments]

        def pairs(rows, blocks):
            return np.matmul(x3[blocks], gram_inv[rows][:, :, None])[:, :, 0]  # (P, 16)

        return SortedBlocks(alphas, m, group, sums, sabs, fine, pairs)

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
