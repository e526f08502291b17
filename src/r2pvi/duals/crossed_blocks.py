"""Sorted blocks of crossed rows ``x_k = e_{a_k} (x) psi_k`` (state features crossed with the
actions), formed batch by batch from ``psi`` and the sort order: neither the ``(n, A m')``
rows nor the ``(n, m')`` state features in sorted order are ever held.

The block sums of :class:`~r2pvi.duals.sorting.SortedBlocks` are linear in the rows: each
block of 16 sorted points is summed in feature space (the powers ``1, alpha, alpha^2`` of
action ``a``'s points times their ``psi``, the other actions' masked out: one batched
product), a batch of blocks at a time into small reused buffers, and only the groups' sums
are kept. The blocks a scan refines and the exact weights of (factor, block) pairs are formed
again from ``psi`` for those blocks only. On the CartPole benchmark (1.9e5 points, d = 162)
this holds 12 MB instead of the 123 MB of sorted ``psi`` and the 48 MB of per-block sums,
whose pages a fresh fit faulted in (a sixth of a cold chi^2 fit).
"""

from __future__ import annotations

import numpy as np

from ._scratch import buffer
from .sorting import BLOCK, SortedBlocks, _block_powers, group_sums, refined_sums

__all__ = ["blocks_from_crossed"]

#: Blocks of 16 sorted points formed per batch (their gathered ``psi``: 128 x 16 x m' floats,
#: 1.3 MB for m' = 81, stays in cache).
BATCH_BLOCKS = 128


def blocks_from_crossed(alphas, psi, src, actions, m, gram_inv, nonneg: bool,
                        moments: int = 3, group: int = 1,
                        scale: np.ndarray | None = None, keep: bool = False,
                        refined=None) -> SortedBlocks:
    """:class:`~r2pvi.duals.sorting.SortedBlocks` of the ridge weights ``M = Lambda^{-1} X^T``
    of crossed rows, the same numbers as
    :func:`~r2pvi.duals.sorting.blocks_from_features` of the rows in sorted order.

    ``psi (n, m')`` the state features (any float dtype, read as float64); ``src (p,)`` the
    row of each sorted point (any index where ``actions`` is -1); ``actions (p,)`` its action,
    -1 for an extra breakpoint or padding (a zero row); ``scale (p,)`` the rows' sample
    weights in sorted order, or None; ``gram_inv = Lambda^{-1}``, block diagonal with
    ``d = A m'`` (a factor's weights read its own action's rows only); ``nonneg``: the rows
    are known non-negative (then ``|X| = X``).

    ``keep``: also keep every block's sums (``16 d moments`` floats a block) for the
    refinements, instead of forming the refined blocks again: for a dual that refines a large
    share of the blocks (DRPVI's TV ball: about 60 % of them every step on CartPole; chi^2
    refines a few). ``refined(share)``, if given, is told the share of the blocks each
    refinement asked for (the caller's cue to keep the sums next time).
    """
    d, mp = gram_inv.shape[0], psi.shape[1]
    n_act = d // mp
    s3, a3 = src.reshape(-1, BLOCK), actions.reshape(-1, BLOCK)
    sc3 = None if scale is None else scale.reshape(-1, BLOCK)
    nb = s3.shape[0]
    a16 = alphas.reshape(nb, BLOCK)

    def block_sums(blocks):
        """``(sums (k, moments, d), |X| sums (k, d))`` of the blocks of 16 ``blocks``
        (indices or a slice), in reused buffers."""
        s = s3[blocks]
        k = s.shape[0]
        x = buffer("crossed.x", (k * BLOCK, mp))
        if psi.dtype == np.float64:
            np.take(psi, s.ravel(), axis=0, mode="clip", out=x)
        else:  # float32 storage: gathered, then widened
            x[...] = np.take(psi, s.ravel(), axis=0, mode="clip")
        if sc3 is not None:
            x *= sc3[blocks].reshape(-1, 1)
        x3 = x.reshape(k, BLOCK, mp)
        # the powers of action a's points (zero on the others') stacked (k, moments, A, 16),
        # so that the product is laid out as the factors: factor a m' + j of power p at
        # [b, p, a m' + j]
        masked = buffer("crossed.masked", (k, moments, n_act, BLOCK))
        pw, acts = _block_powers(a16[blocks], moments, "crossed.powers"), a3[blocks]
        for a in range(n_act):
            np.multiply(pw, acts[:, None, :] == a, out=masked[:, :, a])
        f = buffer("crossed.f", (k, moments, d))
        np.matmul(masked.reshape(k, -1, BLOCK), x3, out=f.reshape(k, moments * n_act, mp))
        fa = f[:, 0] if nonneg else np.matmul(masked[:, 0], np.abs(x3)).reshape(k, d)
        return f, fa

    nc = -(-nb // group)
    csum = np.empty((nc, moments, d))
    cabs = csum[:, 0] if nonneg else np.empty((nc, d))
    if keep:
        kept = buffer("crossed.kept", (nb, moments, d))
        kept_abs = kept[:, 0] if nonneg else buffer("crossed.kept_abs", (nb, d))
    step = max(group, BATCH_BLOCKS // group * group)  # whole groups per batch
    for b0 in range(0, nb, step):
        b1 = min(nb, b0 + step)
        f, fa = block_sums(slice(b0, b1))
        if keep:
            kept[b0:b1] = f
            if not nonneg:
                kept_abs[b0:b1] = fa
        c0, c1 = b0 // group, -(-b1 // group)
        csum[c0:c1] = group_sums(f, group)
        if not nonneg:
            cabs[c0:c1] = group_sums(fa, group)
    # (moments, d, nc) C-ordered, so that the per-factor running sums over blocks read rows;
    # Lambda^{-1} is block diagonal: one action's block at a time
    sums = buffer("ridge.sums", (moments, d, nc))
    abs_inv = np.abs(gram_inv)
    sabs = np.empty((d, nc))
    diagonal = [slice(a * mp, (a + 1) * mp) for a in range(n_act)]
    for blk in diagonal:
        sums[:, blk] = np.matmul(gram_inv[blk, blk], csum[:, :, blk].transpose(1, 2, 0))
        sabs[blk] = abs_inv[blk, blk] @ cabs[:, blk].T

    def sums_of(idx):  # the blocks asked for: kept, or formed again from psi
        if refined is not None:
            refined(idx.size / nb)
        return (kept[idx], kept_abs[idx]) if keep else block_sums(idx)

    def fine(rows, blocks):
        return refined_sums(rows, blocks, group, nb, gram_inv, abs_inv, sums_of, diagonal)

    def pairs(rows, blocks):
        # factor i = (action i // m', feature): its row of Lambda^{-1} on its own block, on
        # the block's psi rows of that action (zero on the others)
        x = np.take(psi, s3[blocks], axis=0, mode="clip").astype(np.float64, copy=False)
        if sc3 is not None:
            x = x * sc3[blocks][:, :, None]
        act = rows // mp
        own = gram_inv[rows].reshape(rows.size, -1, mp)[np.arange(rows.size), act]
        out = np.matmul(x, own[:, :, None])[:, :, 0]
        out *= a3[blocks] == act[:, None]
        return out

    return SortedBlocks(alphas, m, group, sums, sabs, fine, pairs)

