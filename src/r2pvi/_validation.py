"""Argument checks shared by every layer: each raises a clear error naming the argument."""

from __future__ import annotations

import numbers

import numpy as np


def plain(value):
    """``value`` for an error message: NumPy scalars as the Python number they hold, so a
    message reads ``-0.1``, not ``np.float64(-0.1)``."""
    return value.item() if isinstance(value, np.generic) else value


def as_array(x, name: str) -> np.ndarray:
    """``np.asarray(x)``, with a ragged nested list (rows of different lengths) a
    ``ValueError`` naming the argument instead of NumPy's "inhomogeneous shape"."""
    try:
        return np.asarray(x)
    except ValueError as exc:
        detected = str(exc).split("The detected shape was ", 1)
        where = f" (the rows agree up to shape {detected[1].split(' +')[0]})" if len(
            detected) == 2 else ""
        raise ValueError(f"{name} must be a rectangular array, got a ragged "
                         f"{type(x).__name__} whose rows have different lengths{where}; pad "
                         "the rows or pass an ndarray") from None


def as_float_array(x, name: str, ndim: int | None = None, allow_nan: bool = False,
                   copy: bool = True) -> np.ndarray:
    """Return ``x`` as a float64 array (a copy unless ``copy=False``, for callers that only
    read it), checking dtype, dimension and finiteness."""
    raw = as_array(x, name) if not isinstance(x, str) else None
    if raw is None or raw.dtype.kind not in "biuf":
        kind = type(x).__name__ if raw is None else f"an array of dtype {raw.dtype}"
        if raw is not None and raw.dtype.kind == "c":
            raise TypeError(f"{name} must be real, got a complex array")
        raise TypeError(f"{name} must be a numeric (float) array, got {kind}")
    arr = np.array(raw, dtype=np.float64, copy=True) if copy else np.asarray(raw, np.float64)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        what = "infinite" if allow_nan else "NaN or infinite"
        raise ValueError(f"{name} contains {int(bad.sum())} {what} entries; clean the data first")
    return arr


def check_scalar(
    value,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_inclusive: bool = True,
    integer: bool = False,
) -> float | int:
    """Check a real (or integer) scalar parameter against bounds and return it."""
    kind = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kind):
        what = "an integer" if integer else "a real number"
        raise TypeError(f"{name} must be {what}, got {plain(value)!r} ({type(value).__name__})")
    value = float(value) if not integer else int(value)  # type: ignore[call-overload]
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if low is not None:
        if (value < low) if low_inclusive else (value <= low):
            sign = ">=" if low_inclusive else ">"
            raise ValueError(f"{name} must be {sign} {low}, got {value!r}")
    if high is not None and value > high:
        raise ValueError(f"{name} must be <= {high}, got {value!r}")
    return int(value) if integer else float(value)


def check_choice(value, name: str, choices) -> str:
    """Check that ``value`` is one of the allowed strings, case-insensitively (as every
    string option of r2pvi: ``"L1"`` is ``"l1"``, ``"KL"`` is ``"kl"``); returns the
    canonical spelling, one of ``choices``."""
    if isinstance(value, str):
        for choice in choices:
            if value.lower() == choice.lower():
                return choice
    raise ValueError(f"{name} must be one of {sorted(choices)}, got {plain(value)!r}")


def as_index_array(x, name: str, n: int, ndim: int | None = None) -> np.ndarray:
    """Integer indices in ``[0, n)`` as int64 (floats with integer values are accepted)."""
    arr = as_array(x, name)
    if arr.dtype == bool or arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be integer indices, got dtype {arr.dtype}")
    if arr.dtype.kind == "f" and (
        not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr))
    ):
        raise TypeError(f"{name} must be integer indices, got non-integer values")
    arr = arr.astype(np.int64)  # always a copy: the result is the caller's to keep
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() >= n):  # two reductions, no temporaries
        raise ValueError(f"{name} must lie in [0, {n}), got values from {plain(arr.min())} to "
                         f"{plain(arr.max())}")
    return arr
