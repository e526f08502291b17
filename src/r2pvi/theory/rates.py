"""Empirical rates: the slope of ``log SubOpt`` against ``log K`` with a bootstrap interval."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import check_scalar

__all__ = ["SlopeFit", "loglog_slope"]


@dataclass(frozen=True)
class SlopeFit:
    """Least-squares slope of ``log10 mean(y)`` on ``log10 K`` and its bootstrap interval.

    ``slope`` is NaN when fewer than ``min_points`` sizes have a positive mean; ``lo`` and
    ``hi`` are NaN when too few bootstrap resamples could be fitted. ``sizes`` are the K
    used in the fit (those with a positive mean).
    """

    slope: float
    lo: float
    hi: float
    intercept: float
    sizes: tuple

    def contains(self, value: float) -> bool:
        """Whether ``value`` lies in the interval ``[lo, hi]``."""
        return bool(self.lo <= value <= self.hi)


def _fit(logk: np.ndarray, means: np.ndarray) -> tuple[float, float]:
    """Least-squares line through ``(log10 K, log10 mean)``: ``(slope, intercept)``."""
    slope, intercept = np.polyfit(logk, np.log10(means), 1)
    return float(slope), float(intercept)


def _slopes(logk: np.ndarray, means: np.ndarray, fewest: int) -> np.ndarray:
    """Least-squares slopes of every column of ``log10 means (sizes, B)`` on ``logk``, over
    the positive entries of each column; NaN for columns with fewer than ``fewest``."""
    w = (means > 0).astype(float)
    y = np.log10(np.where(means > 0, means, 1.0))
    n = w.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mx = (w * logk[:, None]).sum(axis=0) / n
        my = (w * y).sum(axis=0) / n
        dx = logk[:, None] - mx
        slope = (w * dx * (y - my)).sum(axis=0) / (w * dx * dx).sum(axis=0)
    return np.where(n >= fewest, slope, np.nan)


def loglog_slope(sizes, samples, *, n_boot: int = 1000, level: float = 0.95, seed=0,
                 min_points: int = 3) -> SlopeFit:
    """Fit ``mean(y) ~ C K^slope`` on a log-log scale, with a percentile bootstrap interval.

    The slope of the least-squares line through ``(log10 K, log10 mean_r y_{K,r})`` over the
    sizes whose mean is positive (a mean of 0 has no logarithm: a learned policy that is
    exactly optimal in every replication). The interval resamples the replications of each
    size independently (``n_boot`` times) and refits.

    Parameters
    ----------
    sizes : sequence of float
        Dataset sizes ``K``.
    samples : sequence of array_like
        ``samples[j]`` are the replications' values (>= 0) at ``sizes[j]``.
    n_boot : int, default 1000
    level : float, default 0.95
    seed : int, SeedSequence or Generator, default 0
        Seed of the bootstrap.
    min_points : int, default 3
        Fewest sizes with a positive mean needed for a slope.

    Returns
    -------
    SlopeFit

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.theory import loglog_slope
    >>> rng = np.random.default_rng(0)
    >>> K = [100, 1000, 10000, 100000]
    >>> y = [k ** -0.5 * rng.uniform(0.5, 1.5, size=20) for k in K]
    >>> fit = loglog_slope(K, y)
    >>> round(fit.slope, 2), fit.contains(-0.5)
    (-0.5, True)
    """
    n_boot = int(check_scalar(n_boot, "n_boot", low=1, integer=True))
    level = check_scalar(level, "level", low=0.0, high=1.0, low_inclusive=False)
    sizes = np.asarray(sizes, dtype=float)
    arrays = [np.asarray(s, dtype=float).ravel() for s in samples]
    if len(arrays) != sizes.size:
        raise ValueError(f"got {sizes.size} sizes but {len(arrays)} groups of samples")
    if any(a.size == 0 for a in arrays):
        raise ValueError("every size needs at least one replication")
    means = np.array([a.mean() for a in arrays])
    use = means > 0
    nan = float("nan")
    if use.sum() < min_points:
        return SlopeFit(nan, nan, nan, nan, tuple(sizes[use].tolist()))
    logk = np.log10(sizes)
    slope, intercept = _fit(logk[use], means[use])
    rng = np.random.default_rng(seed)
    resampled = np.stack([
        a[rng.integers(a.size, size=(n_boot, a.size))].mean(axis=1) for a in arrays
    ])  # (sizes, n_boot)
    boot = _slopes(logk, resampled, max(2, min_points - 1))
    boot = boot[np.isfinite(boot)]
    if boot.size < max(10, n_boot // 2):
        lo = hi = nan
    else:
        tail = (1.0 - level) / 2.0
        lo, hi = (float(x) for x in np.quantile(boot, [tail, 1.0 - tail]))
    return SlopeFit(slope, lo, hi, intercept, tuple(sizes[use].tolist()))
