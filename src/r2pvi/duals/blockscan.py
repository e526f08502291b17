"""Branch-and-bound scaffolding over blocks of sorted breakpoints, shared by the piecewise duals.

A :class:`BlockScan` holds, per factor and block of sorted breakpoints, the exact first and
second truncated moments at the block's start and bounds on their change inside the block;
the duals of :mod:`r2pvi.duals.piecewise` bound their objective per (factor, block), refine
the pairs whose bound beats the best value (:func:`_refine`, :meth:`BlockScan.sub_blocks`) and
evaluate the exact segments of the few pairs left (:meth:`BlockScan.segments`).
"""

from __future__ import annotations

import numpy as np

from ._scratch import buffer
from .operator import ExpectationOperator
from .sorting import BLOCK, fine_blocks

__all__ = ["BlockScan", "GROUP"]


class _Level:
    """Blocks of one level of the branch and bound: per (row, block) the exact ``E1``, ``E2``
    at the block start, the weight ``tail`` of the points at or after it, the block's sums
    ``s0`` of ``M`` and ``sabs`` of ``|M|``, and the block's range ``[start, end]`` of alpha
    (broadcastable to the arrays). ``key`` names its work buffers."""

    key = "scan"

    # dE1/dalpha inside a block is the weight of the points above alpha: the weight after the
    # block plus a part of the block's, which lies between the sums of the block's negative and
    # positive weights, (s0 -+ sum |M|) / 2.
    @property
    def slope(self):
        """A bound on ``|dE1/dalpha|`` inside each block (the weight after the block plus the
        block's sum of ``|M|``)."""
        return np.abs(self._tail - self._s0) + self._sabs

    @property
    def b_lo(self):
        """A lower bound on ``dE1/dalpha`` inside each block."""
        return self._tail - 0.5 * (self._s0 + self._sabs)

    @property
    def b_hi(self):
        """An upper bound on ``dE1/dalpha`` inside each block."""
        return self._tail - 0.5 * (self._s0 - self._sabs)

    def slope_bounds(self):
        """``(min(b_lo, 0), max(b_hi, 0))`` in two reused work buffers (the bounds' hot path:
        four passes instead of the properties' six and two more for the clamps)."""
        shape, key = self._s0.shape, self.key
        mid = np.multiply(self._s0, -0.5, out=buffer(key + ".mid", shape))
        mid += self._tail
        half = np.multiply(self._sabs, 0.5, out=buffer(key + ".half", shape))
        hi = np.add(mid, half, out=buffer(key + ".hi", shape))
        np.maximum(hi, 0.0, out=hi)
        lo = np.subtract(mid, half, out=mid)
        np.minimum(lo, 0.0, out=lo)
        return lo, hi


class _SubBlocks(_Level):
    """The ``group`` fine blocks inside each (row, coarse block) pair a scan refines: arrays
    ``(P, group)``; ``blocks`` are the fine blocks' indices (clamped to the last block where
    ``valid`` is False: past the end), ``p0, p1, p2`` their exclusive running sums."""

    key = "sub"


class BlockScan(_Level):
    """Exact branch-and-bound scaffolding over blocks of sorted breakpoints.

    From :meth:`~r2pvi.duals.ExpectationOperator.sorted_blocks` (blocks of 16) it holds, for
    every factor and block of ``16 group`` breakpoints: the exact ``E1 = E([V]_alpha)`` and
    ``E2 = E([V]_alpha^2)`` at the block's first breakpoint (``e1_start``, ``e2_start``), a
    bound ``slope`` on ``|dE1/dalpha|`` inside the block (the weight after the block plus the
    block's sum of ``|M|``), the block's range of alpha ``[start, end]`` (``end`` is the next
    block's start, the largest value for the last), and ``E1``, ``E2`` at the largest value
    (``e1_top``, ``e2_top``, at ``top``). A dual then bounds its objective per (factor, block),
    splits the pairs whose bound beats the best value found into their blocks of 16
    (:meth:`sub_blocks`, the same quantities) and asks :meth:`segments` for the exact segment
    coefficients of the fine pairs that still beat it. With ``group > 1`` the work on all
    (factor, block) pairs shrinks ``group`` times. The (d, nb) arrays live in reused work
    buffers: valid until the next scan in the same thread.
    """

    def __init__(self, E: ExpectationOperator, v, extra=(), second_moment: bool = True,
                 group: int = 1):
        self.group = int(group)
        sb = E.sorted_blocks(v, extra, moments=3 if second_moment else 2, group=self.group)
        self.alphas = sb.alphas
        self._al3 = sb.alphas.reshape(-1, BLOCK)
        self.top = float(sb.alphas[-1])
        # the fine blocks (16 breakpoints each): their sums on demand (sub_blocks)
        self._fine = sb.fine
        self._fine_start = self._al3[:, 0]
        self._fine_end = np.append(self._fine_start[1:], self.top)
        s0, s1, s2, sabs = sb.s0, sb.s1, sb.s2, sb.sabs  # blocks of 16 group
        # Sums over the blocks before each block (exclusive running sums of all the moments
        # in one pass).
        self._p = _exclusive_cumsum(sb.sums, "p")
        self._p0, self._p1 = self._p[0], self._p[1]
        self._p2 = self._p[2] if second_moment else None
        self._total = self._p0[:, -1:] + s0[:, -1:]
        # weight of the points at or after a block start
        self._tail = np.subtract(self._total, self._p0, out=buffer("scan.tail", s0.shape))
        self._s0, self._sabs = s0, sabs
        self.start = self._fine_start[::self.group]
        self.end = np.append(self.start[1:], self.top)
        self.e1_start = np.multiply(self._tail, self.start, out=buffer("scan.e1", s0.shape))
        self.e1_start += self._p1
        self.e1_top = self._p1[:, -1] + s1[:, -1]
        self.e2_start = self.e2_top = None
        if second_moment:
            self.e2_start = np.multiply(self._tail, self.start**2,
                                        out=buffer("scan.e2", s0.shape))
            self.e2_start += self._p2
            self.e2_top = self._p2[:, -1] + s2[:, -1]
        self._pairs = sb.pairs

    def report(self, totals: dict | None) -> None:
        """Put ``E_i(1)`` (``"mass"``) and ``E_i(v)`` (``"mean"``) into ``totals`` (if a dict)."""
        if totals is not None:
            totals["mass"] = self._total[:, 0].copy()
            totals["mean"] = self.e1_top

    def sub_blocks(self, rows, blocks) -> _SubBlocks:
        """The fine blocks (of 16) of the pairs ``(rows, blocks)`` of this scan's blocks:
        :class:`_SubBlocks` with arrays ``(P, group)`` (exact start values from this scan's
        running sums plus the fine block sums before them inside the block)."""
        g = self.group
        nb = self._fine_start.size
        sub = _SubBlocks()
        sub.valid = (blocks[:, None] * g + np.arange(g)) < nb
        # entries past the end repeat the last block: masked by ``valid``
        sub.blocks = fine_blocks(blocks, g, nb)
        sums, sub._sabs = self._fine(rows, blocks)  # (moments, P, group), (P, group)
        sub._s0 = sums[0]
        p = _exclusive_cumsum(sums, None)
        p += self._p[:, rows, blocks][:, :, None]
        sub.p0, sub.p1 = p[0], p[1]
        sub._tail = self._total[rows] - sub.p0
        sub.start = np.where(sub.valid, self._fine_start[sub.blocks], self.top)
        sub.end = np.where(sub.valid, self._fine_end[sub.blocks], self.top)
        sub.e1_start = sub.p1 + sub._tail * sub.start
        sub.p2 = sub.e2_start = None
        if self._p2 is not None:
            sub.p2 = p[2]
            sub.e2_start = sub.p2 + sub._tail * sub.start**2
        return sub

    def segments(self, rows, blocks, prefix=None):
        """Exact coefficients ``(a, b, c, alphas)``, each ``(P, 17)``, on every segment of the
        (factor, fine block) pairs ``(rows, blocks)``: on segment k ``E1 = a_k + b_k alpha``
        and ``E2 = c_k + b_k alpha^2``; the last column is the next block's start, reached by
        the block's last segment (its coefficients repeated). ``c`` is None without the second
        moment. ``prefix``: the pairs' exclusive running sums ``(p0, p1, p2)`` (from
        :meth:`sub_blocks`); None takes this scan's (``group = 1`` only)."""
        if prefix is None:
            if self.group != 1:
                raise ValueError("segments needs the pairs' running sums when group > 1")
            p0, p1 = self._p0[rows, blocks], self._p1[rows, blocks]
            p2 = None if self._p2 is None else self._p2[rows, blocks]
        else:
            p0, p1, p2 = prefix
        wb = self._pairs(rows, blocks)  # (P, 16) exact weights
        ab = self._al3[blocks]
        moments = 2 if p2 is None else 3
        # w, w alpha (and w alpha^2) stacked: their running sums in one product with a
        # triangle of ones (np.cumsum is slower on rows of 16)
        terms = np.empty((moments, wb.shape[0], BLOCK))
        terms[0] = wb
        np.multiply(wb, ab, out=terms[1])
        if p2 is not None:
            np.multiply(terms[1], ab, out=terms[2])
        coef = np.empty((moments, wb.shape[0], BLOCK + 1))
        _running_sums(terms, coef[:, :, :BLOCK], exclusive=False)
        coef[:, :, BLOCK] = coef[:, :, BLOCK - 1]
        b = coef[0]
        b += p0[:, None]
        np.subtract(self._total[rows], b, out=b)
        a = coef[1]
        a += p1[:, None]
        c = None
        if p2 is not None:
            c = coef[2]
            c += p2[:, None]
        al = np.concatenate([ab, self._fine_end[blocks, None]], axis=1)
        return a, b, c, al


# Fine blocks (of 16 breakpoints) per block of the first level of the duals' branch and bound.
GROUP = 4


# Triangles of ones: ``x @ _INCLUSIVE[n]`` and ``x @ _EXCLUSIVE[n]`` are the running sums of
# the rows of ``x (r, n)``, with and without the current entry (small n: one product is faster
# than np.cumsum on many short rows).
_INCLUSIVE = {n: np.triu(np.ones((n, n))) for n in range(1, BLOCK + 1)}
_EXCLUSIVE = {n: np.triu(np.ones((n, n)), 1) for n in range(1, BLOCK + 1)}


def _running_sums(s, out, exclusive):
    """Running sums of ``s`` along its last axis into ``out``: ``sum_{k <= j}`` (``sum_{k <
    j}`` if ``exclusive``). Up to 16 entries by one product with a triangle of ones, unless
    that meets an infinite entry (``inf * 0``: NaN where np.cumsum is exact)."""
    n = s.shape[-1]
    if n <= BLOCK:
        np.matmul(s, (_EXCLUSIVE if exclusive else _INCLUSIVE)[n], out=out)
        if np.isfinite(out).all():
            return out
    if not exclusive:
        return np.cumsum(s, axis=-1, out=out)
    out[..., 0] = 0.0
    np.cumsum(s[..., :-1], axis=-1, out=out[..., 1:])
    return out


def _exclusive_cumsum(s, key):
    """``p[..., j] = sum_{k < j} s[..., k]`` (into a reused work buffer when ``key`` is
    given)."""
    p = np.empty(s.shape) if key is None else buffer("scan." + key, s.shape)
    return _running_sums(s, p, exclusive=True)


def _refine(scan, rows, blocks, best, start_value, bound):
    """The second level: the fine blocks of the pairs ``(rows, blocks)``; their exact start
    values raise ``best``; returns the fine pairs ``(rows, blocks, prefix)`` whose bound still
    beats it. ``bound(sub, rows, start)`` gets the start values (formed once)."""
    sub = scan.sub_blocks(rows, blocks)
    vals = start_value(sub, rows)
    upper = bound(sub, rows, vals)
    vals[~sub.valid] = -np.inf
    np.maximum.at(best, rows, vals.max(axis=1))
    keep = (upper > best[rows, None]) & sub.valid
    pair, k = np.nonzero(keep)
    prefix = tuple(None if x is None else x[pair, k] for x in (sub.p0, sub.p1, sub.p2))
    return rows[pair], sub.blocks[pair, k], prefix
