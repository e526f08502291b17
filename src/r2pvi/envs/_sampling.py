"""Seeded random number generators and vectorized categorical sampling."""

from __future__ import annotations

import numbers

import numpy as np

__all__ = ["as_generator", "sample_categorical", "sample_rows", "check_count"]


def as_generator(seed) -> np.random.Generator:
    """``numpy.random.default_rng(seed)``: None, an int, a SeedSequence or a Generator
    (returned as is, so that a caller's stream continues)."""
    if isinstance(seed, bool):
        raise TypeError("seed must be None, an integer, a SeedSequence or a numpy Generator")
    if isinstance(seed, numbers.Integral) and seed < 0:
        raise ValueError(f"seed must be >= 0 (NumPy seeds are non-negative), got {seed}")
    if seed is None or isinstance(seed, numbers.Integral | np.random.SeedSequence):
        return np.random.default_rng(seed)
    if isinstance(seed, np.random.Generator):
        return seed
    raise TypeError(
        f"seed must be None, an integer, a SeedSequence or a numpy Generator, got {seed!r}"
    )


def sample_categorical(probs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw per row of ``probs (n, m)`` (rows are distributions), by inverse CDF.

    The uniform is scaled by the row total, so a draw never lands on a zero-probability
    category even when the cumulative sum ends slightly below 1.
    """
    cdf = np.cumsum(probs, axis=1)
    u = rng.random(probs.shape[0]) * cdf[:, -1]
    return (cdf <= u[:, None]).sum(axis=1)


def sample_rows(table: np.ndarray, rows: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw from each distribution ``table[rows[k]]``: the same draws as
    ``sample_categorical(table[rows], rng)``, without gathering an ``(n, m)`` array.

    The cumulative sums are taken once per row of the small ``table (R, m)`` (the same
    sequential sums as per sample); with few categories the draws are counted column by
    column (``m`` gathers of ``n`` values instead of a strided ``(n, m)`` pass).

    Examples
    --------
    >>> import numpy as np
    >>> table = np.array([[0.5, 0.5, 0.0], [0.0, 0.1, 0.9]])
    >>> rows = np.array([0, 1, 1, 0, 1])
    >>> a = sample_rows(table, rows, np.random.default_rng(3))
    >>> b = sample_categorical(table[rows], np.random.default_rng(3))
    >>> bool((a == b).all())
    True
    """
    cdf = np.cumsum(table, axis=1)
    m = cdf.shape[1]
    columns = np.ascontiguousarray(cdf.T)  # columns[j]: P(category <= j) of every row
    u = rng.random(rows.shape[0]) * columns[m - 1].take(rows)
    if m > 16:
        return (cdf[rows] <= u[:, None]).sum(axis=1)
    out = (columns[0].take(rows) <= u).astype(np.int64)
    for j in range(1, m):  # the last column counts only on round-off, as in the row sum
        out += columns[j].take(rows) <= u
    return out


def check_count(value, name: str) -> int:
    """A positive integer count (trajectories, episodes)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)
