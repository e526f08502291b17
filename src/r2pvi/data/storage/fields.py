"""The field protocol: a step-major array ``(H, K, ...)`` read by step and range of
trajectories, wherever it is (one module per storage kind implements it: ``memory``,
``files``, ``dask_arrays``, ``observations``)."""

from __future__ import annotations

import numpy as np

from ._finite import Origin, array_origin

# Trajectories per chunk when streaming a step: about 1 MB (taken actions) and 2 MB (next
# states, A = 2) of float64 per chunk for d = 30, about one core's L2. Measured at K = 1e6
# from the page cache (TV and KL fits from disk, min of 3-4 interleaved rounds, shared
# machine): 4096 rows 8-12% less CPU than 2048 (per-chunk Python and call overhead), 8192
# no better than 4096.
CHUNK = 1 << 12


def _float_dtype(dtype) -> np.dtype:
    """float32 or float64, else a ValueError naming the choices."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt not in (np.float32, np.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    return dt


def _as_float64(a):
    if a is None:
        return None
    return np.ascontiguousarray(a, dtype=np.float64)


def widen_range(bounds: tuple[float, float], values: np.ndarray) -> tuple[float, float]:
    """``bounds (low, high)`` widened to hold ``values`` (finite, checked by the caller): how
    the rewards' range is accumulated chunk by chunk where validation reads them anyway."""
    if values.size == 0:
        return bounds
    return min(bounds[0], float(np.min(values))), max(bounds[1], float(np.max(values)))


class Field:
    """A step-major array ``(H, K, ...)`` read by step and range of trajectories."""

    shape: tuple
    dtype: np.dtype

    def origin(self, name: str) -> Origin:
        """Where the numbers of the field ``name`` come from (named by a fit's errors)."""
        return array_origin(name)

    def read(self, h: int, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Rows ``[h, start:stop]`` as an ndarray (may be a read-only view)."""
        raise NotImplementedError

    def lazy(self):
        """The whole field ``(H, K, ...)`` without reading it (a view or memory map)."""
        raise NotImplementedError

    def take(self, idx: np.ndarray) -> np.ndarray:
        """The trajectories ``idx`` of every step, ``(H, len(idx), ...)``, in memory."""
        return np.stack([self.read(h)[idx] for h in range(self.shape[0])])

    def chunks(self, h: int, chunk: int):
        """``(start, stop, rows)`` over the trajectories of step ``h``."""
        K = self.shape[1]
        for s in range(0, K, chunk):
            e = min(K, s + chunk)
            yield s, e, self.read(h, s, e)


def readonly(a):
    """A read-only view of the ndarray ``a`` (anything else, e.g. a Dask array, as it is)."""
    if not isinstance(a, np.ndarray):
        return a  # a Dask array: immutable already
    v = a.view()
    v.flags.writeable = False
    return v
