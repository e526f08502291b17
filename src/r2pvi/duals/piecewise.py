"""Exact maximization of the chi^2 dual objective over the truncation level alpha.

For one factor, with ``E1(alpha) = E([V]_alpha)`` and ``E2(alpha) = E([V]_alpha^2)``, the paper's
estimated chi^2 dual (eq. (parameter estimation x2)) maximizes

    g(alpha) = c1(E1) + (c1(E1)^2 - c2(E2)) / (4 lam),     c1, c2: optional clips,

over ``alpha`` in ``[min v, max v]``. On the segment between two consecutive sorted values,
``E1 = A + B alpha`` and ``E2 = C + B alpha^2``, so ``g`` is piecewise quadratic: its maximum
is at a breakpoint, at a point where a clip becomes active, or at the stationary point of a
piece. :func:`segments_max` evaluates all of them for every row of coefficient arrays.

:func:`blockwise_max` is the same maximization, exact, organised as branch and bound: the
objective is evaluated exactly at the first breakpoint of every block of 64 (``GROUP`` blocks
of 16) and bounded on each block from block sums of the weights; the (factor, block) pairs
whose bound beats the best value found are split into their blocks of 16, evaluated and
bounded the same way, and :func:`segments_max` runs only on the fine pairs whose bound still
beats it. The cost is O(n d) reductions (the block sums) instead of three O(n d) prefix sums
and a dozen passes; the work on every (factor, block) pair is on d n / 64 pairs, and the pairs
refined are few.
"""

from __future__ import annotations

import numpy as np

from ._scratch import buffer
from .operator import ExpectationOperator
from .ranges import clip
from .sorting import BLOCK, fine_blocks

__all__ = [
    "chi2_objective", "segments_max", "blockwise_max", "dense_max", "tv_ball_max", "BlockScan",
]


def chi2_objective(e1, e2, lam, mean_clip=None, second_clip=None, out=None):
    """``c1(E1) + (c1(E1)^2 - c2(E2)) / (4 lam)`` (inputs unchanged; ``out`` optional)."""
    big = out is not None
    if mean_clip is not None:
        e1 = clip(e1, *mean_clip, out=buffer("chi2.e1c", np.shape(e1)) if big else None)
    if second_clip is not None:
        e2 = clip(e2, *second_clip, out=buffer("chi2.e2c", np.shape(e2)) if big else None)
    out = np.multiply(e1, e1, out=out)
    out -= e2
    out *= 0.25 / lam
    out += e1
    return out


def _sign_changes(f):
    """(row, segment) pairs where ``f`` (known at breakpoints, monotone on each segment)
    changes sign, so that a root lies in the segment. Touching 0 exactly at a breakpoint gives
    a harmless extra candidate (breakpoints are evaluated anyway)."""
    sign = np.signbit(f)
    return np.nonzero(sign[:, :-1] != sign[:, 1:])


def segments_max(a, b, c, alphas, lam, mean_clip=None, second_clip=None, *, scratch=False):
    """Row-wise maximum of the chi^2 objective over piecewise coefficients.

    ``a, b, c`` are ``(rows, m)``: on segment k (``alpha`` in ``[alphas_k, alphas_{k+1}]``)
    ``E1 = a_k + b_k alpha``, ``E2 = c_k + b_k alpha^2``; ``alphas`` is ``(m,)`` or
    ``(rows, m)``, increasing along the last axis, and no segment may contain 0 in its
    interior (``E2`` is then monotone on each segment). Returns ``(rows,)``.
    """
    shape = a.shape
    al = np.broadcast_to(alphas, shape)
    tmp = (lambda key: buffer(key, shape)) if scratch else (lambda key: None)
    e1 = np.multiply(b, alphas, out=tmp("chi2.e1"))
    e1 += a
    e2 = np.multiply(b, alphas * alphas, out=tmp("chi2.e2"))
    e2 += c
    ranges = {"e1": (e1.min(), e1.max()), "e2": (e2.min(), e2.max())}

    def active(clip, which):
        """The clip, or None when no breakpoint value reaches it (then it never binds)."""
        if clip is None:
            return None
        lo, hi = ranges[which]
        return clip if lo < clip[0] or hi > clip[1] else None

    best = chi2_objective(e1, e2, lam, active(mean_clip, "e1"), active(second_clip, "e2"),
                          out=tmp("chi2.g")).max(axis=1)
    if shape[1] < 2:
        return best
    seg_a, seg_b, seg_c = a[:, :-1], b[:, :-1], c[:, :-1]
    left, right = al[:, :-1], al[:, 1:]

    def crossings_of(which, f, level):
        lo, hi = ranges[which]
        if not lo < level < hi:  # most clip levels are never crossed: one global test
            return None
        return _sign_changes(np.subtract(f, level, out=tmp("chi2.shifted")))

    # A segment with B = 0 is flat; opposite-signed zeros at its ends can still flag a
    # "crossing", whose candidate 0/0 is then clamped into the segment: harmless, silenced.
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = []
        # Stationary point, no clip active: g' = B (1 + (E1 - alpha) / (2 lam)) = 0, i.e. where
        # E1 - alpha + 2 lam (linear on the segment) changes sign.
        i, k = _sign_changes(np.subtract(e1, al - 2.0 * lam, out=tmp("chi2.shifted")))
        candidates.append((i, k, (seg_a[i, k] + 2.0 * lam) / (1.0 - seg_b[i, k])))
        if second_clip is not None:
            # Stationary point with E2 clipped (constant): g' = B (1 + E1 / (2 lam)) = 0.
            found = crossings_of("e1", e1, -2.0 * lam)
            if found is not None:
                i, k = found
                candidates.append((i, k, -(seg_a[i, k] + 2.0 * lam) / seg_b[i, k]))
            for bound in second_clip:  # E2 = C + B alpha^2 reaches a clip bound
                found = crossings_of("e2", e2, bound)
                if found is not None:
                    i, k = found
                    root = np.sqrt(np.maximum((bound - seg_c[i, k]) / seg_b[i, k], 0.0))
                    side = np.where(left[i, k] + right[i, k] >= 0.0, 1.0, -1.0)
                    candidates.append((i, k, side * root))
        if mean_clip is not None:
            for bound in mean_clip:  # E1 = A + B alpha reaches a clip bound
                found = crossings_of("e1", e1, bound)
                if found is not None:
                    i, k = found
                    candidates.append((i, k, (bound - seg_a[i, k]) / seg_b[i, k]))
    for i, k, alpha in candidates:
        if i.size == 0:
            continue
        alpha = np.clip(np.nan_to_num(alpha, nan=0.0, posinf=np.inf, neginf=-np.inf),
                        left[i, k], right[i, k])
        vals = chi2_objective(seg_a[i, k] + seg_b[i, k] * alpha,
                              seg_c[i, k] + seg_b[i, k] * alpha**2, lam, mean_clip, second_clip)
        np.maximum.at(best, i, vals)
    return best


def dense_max(E: ExpectationOperator, v, lam, mean_clip=None, second_clip=None, extra=()):
    """Every breakpoint and candidate of every factor, from full prefix sums (reference path)."""
    cum = E.truncation_cumulants(v, extra)
    return segments_max(cum.a, cum.b, cum.c, cum.alphas, lam, mean_clip, second_clip,
                        scratch=True)


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


def blockwise_max(E: ExpectationOperator, v, lam, mean_clip=None, second_clip=None, extra=(),
                  totals: dict | None = None, group: int | None = None):
    """The exact chi^2 maximum by branch and bound over blocks of breakpoints (module doc):
    blocks of ``16 group`` breakpoints first (``GROUP`` by default), then the blocks of 16
    inside those whose bound beats the best value, then the exact segments.

    ``totals``, a dict, receives ``"mass"`` and ``"mean"``: ``E_i(1)`` and ``E_i(v)`` from the
    block sums (no further pass over the data)."""
    scan = BlockScan(E, v, extra, group=GROUP if group is None else group)
    scan.report(totals)
    shape = scan.e1_start.shape
    best = chi2_objective(scan.e1_start, scan.e2_start, lam, mean_clip, second_clip,
                          out=buffer("scan.g", shape)).max(axis=1)
    top = chi2_objective(scan.e1_top, scan.e2_top, lam, mean_clip, second_clip)
    best = np.maximum(best, top)
    upper = _chi2_block_bounds(scan, lam, mean_clip, second_clip)
    rows, blocks = np.nonzero(upper > best[:, None])
    prefix = None
    if rows.size and scan.group > 1:
        rows, blocks, prefix = _refine(
            scan, rows, blocks, best,
            lambda sub, r: chi2_objective(sub.e1_start, sub.e2_start, lam, mean_clip,
                                          second_clip),
            lambda sub, r, start: _chi2_block_bounds(sub, lam, mean_clip, second_clip))
    if rows.size:
        a, b, c, al = scan.segments(rows, blocks, prefix)
        np.maximum.at(best, rows, segments_max(a, b, c, al, lam, mean_clip, second_clip))
    return best


def _chi2_block_bounds(scan: _Level, lam, mean_clip, second_clip):
    """An upper bound on the chi^2 objective on each (row, block) of a level.

    E1 lies within the slope bounds times the block's width of its start value, E2 above its
    start value plus ``min(B, 0) d(alpha^2)``; g grows with E1 where the clipped E1 is at least
    ``-2 lam`` (then the upper end alone) and is convex in E1 (else the larger end), and falls
    with E2. ``dE2 = B d(alpha^2)`` with ``alpha^2`` monotone on a block that does not
    straddle 0 (else the cruder bound with ``|B| <= slope``)."""
    shape, key = scan.e1_start.shape, scan.key
    lo, hi = scan.slope_bounds()  # min(b_lo, 0), max(b_hi, 0)
    span1 = scan.end - scan.start
    delta2 = scan.end**2 - scan.start**2
    q = 0.25 / lam
    monotone = mean_clip is not None and mean_clip[0] >= -2.0 * lam and np.isfinite(q)
    if not monotone:
        e1_lo = np.multiply(lo, span1, out=buffer(key + ".e1lo", shape))
        e1_lo += scan.e1_start
    # E2's lower end: B d(alpha^2) >= min(b_lo, 0) d(alpha^2) where d(alpha^2) >= 0 and
    # max(b_hi, 0) d(alpha^2) where it is negative.
    e2_lo = np.multiply(lo, np.maximum(delta2, 0.0), out=buffer(key + ".e2lo", shape))
    negative = np.min(scan.start) < 0.0
    if negative:
        e2_lo += hi * np.minimum(delta2, 0.0)
    e2_lo += scan.e2_start
    if negative:
        straddle = np.broadcast_to((scan.start < 0) & (scan.end > 0), shape)
        if straddle.any():
            span2 = np.broadcast_to(np.maximum(scan.start**2, scan.end**2), shape)
            e2_lo[straddle] = (scan.e2_start - scan.slope * span2)[straddle]
    e1_hi = np.multiply(hi, span1, out=hi)
    e1_hi += scan.e1_start
    upper = _g_of_mean(e1_hi, q, mean_clip, key + ".up")
    if not monotone:
        np.maximum(upper, _g_of_mean(e1_lo, q, mean_clip, key + ".up2"), out=upper)
    if second_clip is not None:
        clip(e2_lo, *second_clip, out=e2_lo)
    e2_lo *= q
    upper -= e2_lo
    return upper


def _g_of_mean(e1, q, mean_clip, key):
    """``c + q c^2`` with ``c`` the clipped ``e1`` (clipped in place), into a work buffer."""
    if mean_clip is not None:
        clip(e1, *mean_clip, out=e1)
    g = np.multiply(e1, e1, out=buffer(key, e1.shape))
    g *= q
    g += e1
    return g


def _tv_start_values(scan: _Level, rho_col):
    """``E1 - rho alpha`` at every block start of a level."""
    return scan.e1_start - rho_col * scan.start


def _tv_block_bounds(scan: _Level, rho_col, f_start):
    """``f_start + width max(b_hi - rho, 0)``: d/dalpha (E1 - rho alpha) = B - rho <= b_hi - rho
    inside a block (and ``max(max(b_hi, 0) - rho, 0) = max(b_hi - rho, 0)`` as rho >= 0)."""
    upper = np.subtract(scan.slope_bounds()[1], rho_col,
                        out=buffer(scan.key + ".up", f_start.shape))
    np.maximum(upper, 0.0, out=upper)
    upper *= scan.end - scan.start
    upper += f_start
    return upper


def tv_ball_max(E: ExpectationOperator, v, rho, totals: dict | None = None,
                group: int | None = None) -> np.ndarray:
    """``max_k E_i([V]_alpha_k) - rho_i alpha_k`` over every breakpoint ``alpha_k`` (the
    piecewise-linear TV-ball dual without its constant), by the same branch and bound;
    ``totals`` and ``group`` as in :func:`blockwise_max`."""
    scan = BlockScan(E, v, second_moment=False, group=GROUP if group is None else group)
    scan.report(totals)
    rho_col = rho[:, None]
    f_start = _tv_start_values(scan, rho_col)
    best = np.maximum(f_start.max(axis=1), scan.e1_top - rho * scan.top)
    upper = _tv_block_bounds(scan, rho_col, f_start)
    rows, blocks = np.nonzero(upper > best[:, None])
    prefix = None
    if rows.size and scan.group > 1:
        rows, blocks, prefix = _refine(
            scan, rows, blocks, best,
            lambda sub, r: _tv_start_values(sub, rho[r, None]),
            lambda sub, r, start: _tv_block_bounds(sub, rho[r, None], start))
    if rows.size:
        a, b, _, al = scan.segments(rows, blocks, prefix)
        vals = (a + (b - rho[rows, None]) * al).max(axis=1)
        np.maximum.at(best, rows, vals)
    return best
