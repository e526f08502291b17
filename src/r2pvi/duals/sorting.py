"""Sorting kernels of the piecewise duals: one sort of the values, prefix sums by blocks.

The piecewise duals (TV and chi^2 regularized, the TV ball) need, for every breakpoint
``alpha`` (a value of ``V``), sums of the operator's weights over the points below it. The
values are sorted once (:func:`sort_order`, :func:`sort_breakpoints`); weights in sorted order
are summed by blocks of ``BLOCK = 16`` points (:class:`SortedBlocks`, for the branch and bound
over blocks) or by full prefix sums (:func:`prefix_sums`, :class:`TruncationCumulants`).
"""

from __future__ import annotations

import numpy as np

from ._scratch import buffer

__all__ = [
    "BLOCK",
    "prefix_sums",
    "sort_order",
    "sort_breakpoints",
    "SortedBlocks",
    "fine_blocks",
    "group_sums",
    "TruncationCumulants",
    "blocks_from_weights",
    "blocks_from_features",
    "cumulants_from_weights",
]

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


def sort_order(v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """An ``order`` with ``v[order]`` non-decreasing (a permutation, like ``np.argsort(v)``;
    equal values in index order, except that every -0.0 comes before every 0.0), and
    ``v[order]`` written into ``out`` if given.

    One ``np.sort`` of 64-bit keys instead of ``np.argsort`` (faster for large n): the bits of
    each float made order-preserving as integers, their last ``b`` bits replaced by the index
    (``2^b >= n``). Values that differ in those bits only come out in
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


def _block_powers(alphas: np.ndarray, moments: int = 3, key: str = "blocks.powers") -> np.ndarray:
    """``(nb, moments, 16)``: 1, alpha (and alpha^2) of every sorted point, by block (in the
    reused buffer ``key``)."""
    a3 = alphas.reshape(-1, BLOCK)
    out = buffer(key, (a3.shape[0], moments, BLOCK))
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
    head = out[:full // group]  # strided adds: np.add.reduceat is slower here
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


def blocks_from_weights(alphas, weights, m, moments: int = 3, group: int = 1) -> SortedBlocks:
    """:class:`SortedBlocks` from the weight columns in sorted order ``weights (d, p)`` (see
    :meth:`~r2pvi.duals.ExpectationOperator.sorted_blocks`)."""
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


def blocks_from_features(alphas, xs, m, gram_inv, nonneg: bool, moments: int = 3,
                         group: int = 1) -> SortedBlocks:
    """:class:`SortedBlocks` of the ridge weights ``M = Lambda^{-1} X^T`` from the (weighted)
    feature rows in sorted order ``xs (p, d)`` and ``gram_inv = Lambda^{-1}``; ``nonneg``:
    the rows are known non-negative (then ``|X| = X``). (Rows crossed with the actions, never
    formed: :func:`~r2pvi.duals.crossed_blocks.blocks_from_crossed`.)

    ``M`` is linear in the features: each block of 16 is summed in feature space (one batched
    product), those sums are added up by groups, and only the groups' ``(nc, d)`` sums are
    mapped by ``Lambda^{-1}``; the sums of blocks of 16 are mapped on demand, for the (factor,
    block) pairs a scan refines. ``|M|`` is bounded by ``|Lambda^{-1}| |X|``; exact weights are
    formed only for the pairs asked for: row i of ``Lambda^{-1}`` times the block's 16 rows.
    """
    d = gram_inv.shape[0]
    x3 = xs.reshape(-1, BLOCK, xs.shape[1])
    nb = x3.shape[0]
    powers = _block_powers(alphas, moments)  # (nb, moments, 16)
    fsum = buffer("ridge.fsum", (nb, moments, d))  # (nb, moments, d)
    np.matmul(powers, x3, out=fsum)
    fabs = fsum[:, 0] if nonneg else np.abs(x3).sum(axis=1)  # (nb, d)
    csum = group_sums(fsum, group)
    # (moments, d, nc) C-ordered, so that the per-factor running sums over blocks read rows:
    # Lambda^{-1} times the transposed sums, straight into a work buffer (BLAS reads the
    # transposed operand; no transposing copy).
    sums = buffer("ridge.sums", (moments, d, csum.shape[0]))
    abs_inv = np.abs(gram_inv)
    cabs = csum[:, 0] if nonneg else group_sums(fabs, group)
    np.matmul(gram_inv, csum.transpose(1, 2, 0), out=sums)
    sabs = abs_inv @ cabs.T

    def fine(rows, blocks):
        return refined_sums(rows, blocks, group, nb, gram_inv, abs_inv,
                            lambda idx: (fsum[idx], fabs[idx]))

    def pairs(rows, blocks):
        return np.matmul(x3[blocks], gram_inv[rows][:, :, None])[:, :, 0]  # (P, 16)

    return SortedBlocks(alphas, m, group, sums, sabs, fine, pairs)


def refined_sums(rows, blocks, group: int, nb: int, gram_inv, abs_inv, feature_sums,
                 diagonal_blocks=None):
    """The ``fine(rows, blocks)`` of :class:`SortedBlocks` built from feature sums:
    ``Lambda^{-1}`` (and ``|Lambda^{-1}|``) on the feature sums of the blocks of 16 inside the
    distinct blocks of ``16 group`` asked for only (U of them; a mask and its running count
    instead of ``np.unique``'s sort). ``feature_sums(idx)`` gives ``(sums (k, moments, d),
    |X| sums (k, d))`` of the blocks of 16 ``idx``; ``nb`` counts the blocks of 16;
    ``diagonal_blocks``: slices of the factors when ``Lambda^{-1}`` is block diagonal (rows
    crossed with the actions), mapped one block at a time (``A`` times fewer products)."""
    seen = np.zeros(-(-nb // group), dtype=bool)
    seen[blocks] = True
    ub = np.flatnonzero(seen)
    inv = (np.cumsum(seen) - 1)[blocks]
    idx = fine_blocks(ub, group, nb).ravel()  # (U group,)
    f, fa = feature_sums(idx)
    moments, d = f.shape[1], f.shape[2]
    mapped = np.empty((moments + 1, d, idx.size))
    for blk in [slice(0, d)] if diagonal_blocks is None else diagonal_blocks:
        np.matmul(gram_inv[blk, blk], f[:, :, blk].transpose(1, 2, 0), out=mapped[:moments, blk])
        np.matmul(abs_inv[blk, blk], fa[:, blk].T, out=mapped[moments, blk])
    out = mapped.reshape(moments + 1, d, ub.size, group)[
        :, rows[:, None], inv[:, None], np.arange(group)]  # (moments + 1, P, group)
    return out[:moments], out[moments]


def cumulants_from_weights(alphas, weights, m) -> TruncationCumulants:
    """:class:`TruncationCumulants` from the weight columns in sorted order ``weights (d, p)``
    (see :meth:`~r2pvi.duals.ExpectationOperator.truncation_cumulants`)."""
    d, padded = weights.shape
    # M, M v and M v^2 (columns in sorted order) share one buffer, so that one blocked prefix
    # sum (a GEMM, faster than np.cumsum here) serves all three.
    stacked = buffer("cumulants.stacked", (3, d, padded))
    stacked[0] = weights
    np.multiply(stacked[0], alphas, out=stacked[1])
    np.multiply(stacked[1], alphas, out=stacked[2])
    sums = prefix_sums(stacked.reshape(3 * d, padded)).reshape(3, d, padded)
    head, a, c = sums[0, :, :m], sums[1, :, :m], sums[2, :, :m]
    b = np.subtract(head[:, -1:], head, out=head)
    return TruncationCumulants(alphas[:m], a, b, c)
