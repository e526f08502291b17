"""Seeded random number generators and vectorized categorical sampling."""

from __future__ import annotations

import numbers

import numpy as np

__all__ = ["as_generator", "sample_categorical", "check_count"]


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


def check_count(value, name: str) -> int:
    """A positive integer count (trajectories, episodes)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)
