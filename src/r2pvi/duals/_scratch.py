"""Reusable work buffers for the hot loops of the piecewise and general duals.

A fresh large NumPy array is mapped from the operating system page by page, and for the
duals' (d, n) temporaries those page faults can cost more than the arithmetic done on them
(docs/benchmarks.md). The duals therefore draw their temporaries from a thread-local pool
that the engine empties when a fit ends.
"""

from __future__ import annotations

import math
import threading

import numpy as np

_local = threading.local()


def buffer(key: str, shape: tuple[int, ...]) -> np.ndarray:
    """An uninitialized C-contiguous float64 array of ``shape``, reused across calls with the
    same key: a view of the key's memory, which grows only when a call asks for more (so
    that calls with varying shapes, e.g. the active factors of an iteration, fault no pages).

    The content is valid until the next call with the same key in the same thread.
    """
    pool = getattr(_local, "pool", None)
    if pool is None:
        pool = _local.pool = {}
    size = math.prod(shape)
    buf = pool.get(key)
    if buf is None or buf.size < size:
        buf = pool[key] = np.empty(size)
    return buf[:size].reshape(shape)


def release() -> None:
    """Drop every buffer of this thread (called at the end of a fit)."""
    _local.pool = {}
