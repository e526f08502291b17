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
from .blockscan import GROUP, BlockScan, _Level, _refine
from .operator import ExpectationOperator
from .ranges import clip

__all__ = ["chi2_objective", "segments_max", "blockwise_max", "dense_max", "tv_ball_max"]


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


def blockwise_max(E: ExpectationOperator, v, lam, mean_clip=None, second_clip=None, extra=(),
                  totals: dict | None = None, group: int | None = None, ceiling=None):
    """The exact chi^2 maximum by branch and bound over blocks of breakpoints (module doc):
    blocks of ``16 group`` breakpoints first (``GROUP`` by default), then the blocks of 16
    inside those whose bound beats the best value, then the exact segments.

    ``totals``, a dict, receives ``"mass"`` and ``"mean"``: ``E_i(1)`` and ``E_i(v)`` from the
    block sums (no further pass over the data). ``ceiling (d,)``, optional: the result is
    ``min(maximum, ceiling)``, and a factor whose value at the block starts already reaches
    its ceiling is not searched further."""
    scan = BlockScan(E, v, extra, group=GROUP if group is None else group)
    scan.report(totals)
    shape = scan.e1_start.shape
    best = chi2_objective(scan.e1_start, scan.e2_start, lam, mean_clip, second_clip,
                          out=buffer("scan.g", shape)).max(axis=1)
    top = chi2_objective(scan.e1_top, scan.e2_top, lam, mean_clip, second_clip)
    best = np.maximum(best, top)
    if ceiling is not None:
        done = best >= ceiling
        best[done] = np.inf  # no block beats it: not refined
        return np.minimum(_blockwise_search(scan, best, lam, mean_clip, second_clip), ceiling)
    return _blockwise_search(scan, best, lam, mean_clip, second_clip)


def _blockwise_search(scan, best, lam, mean_clip, second_clip):
    """The branch and bound of :func:`blockwise_max` from the best values ``best`` found at
    the block starts (raised in place)."""
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
