"""The field protocol: a step-major array ``(H, K, ...)`` read by step and range of
trajectories, wherever it is (one module per storage kind implements it: ``memory``,
``files``, ``dask_arrays``, ``observations``)."""

from __future__ import annotations

import numpy as np

from ._finite import Origin, array_origin

# Trajectories per chunk when streaming a step: about 1 MB (taken actions) and 2 MB (next
# states, A = 2) of float64 per chunk for d = 30, about one core's L2; fewer rows pay more
# per-chunk Python and call overhead, more gain nothing (measured: docs/architecture.md,
# "Storage internals").
CHUNK = 1 << 12


def as_float64_chunks(chunks, rows: int):
    """``(start, stop, rows)`` of ``chunks`` with ``rows`` float64 and C-contiguous: the
    chunk itself when it is, else a copy in one reused buffer (of ``rows`` rows at least: no
    fresh allocation, so no page faults, per chunk)."""
    f64 = None
    for s, e, x in chunks:
        if x.dtype != np.float64 or not x.flags.c_contiguous:
            if f64 is None or f64.shape[0] < e - s:
                f64 = np.empty((max(e - s, rows),) + x.shape[1:])
            np.copyto(f64[: e - s], x)
            x = f64[: e - s]
        yield s, e, x


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
    """A step-major array ``(H, K, ...)`` read by step and range of trajectories.

    Besides the reads, a field offers what a fit needs of a step's rows, formed where the
    numbers are (the engine never asks which kind it holds): :meth:`step_rows` (a step's rows
    whole, dense float64 or sparse), :meth:`float64_chunks` (by chunk), :meth:`times`
    (``Phi_h z``), :meth:`products` (sums formed remotely, or None), and facts
    (:meth:`bounds`, :meth:`nonnegative`). The generic implementations here read chunks;
    the kinds override what they can do better.
    """

    shape: tuple
    dtype: np.dtype
    storage = "memory"  # where the numbers live (OfflineDataset.storage)
    dense_rows = True  # a step's rows are an ndarray (False: sparse rows)

    def origin(self, name: str) -> Origin:
        """Where the numbers of the field ``name`` come from (named by a fit's errors)."""
        return array_origin(name)

    def read(self, h: int, start: int = 0, stop: int | None = None, out=None) -> np.ndarray:
        """Rows ``[h, start:stop]`` as an ndarray (may be a read-only view); ``out``, a buffer
        of the right shape and dtype, may be filled and returned instead (files)."""
        raise NotImplementedError

    def lazy(self):
        """The whole field ``(H, K, ...)`` without reading it (a view or memory map)."""
        raise NotImplementedError

    def take(self, idx: np.ndarray) -> np.ndarray:
        """The trajectories ``idx`` of every step, ``(H, len(idx), ...)``, in memory."""
        return np.stack([self.read(h)[idx] for h in range(self.shape[0])])

    def subset(self, idx: np.ndarray, name: str) -> Field:
        """The field of the trajectories ``idx`` (``OfflineDataset.subset``), in memory."""
        raise NotImplementedError

    def describe(self) -> str:
        """What a dataset's repr adds about the field ("" but for sparse rows)."""
        return ""

    def chunks(self, h: int, chunk: int):
        """``(start, stop, rows)`` over the trajectories of step ``h``."""
        K = self.shape[1]
        for s in range(0, K, chunk):
            e = min(K, s + chunk)
            yield s, e, self.read(h, s, e)

    # ------------------------------------------------------------------ what a fit reads
    def float64_chunks(self, h: int, chunk: int):
        """``(start, stop, rows)`` over step ``h`` with ``rows`` float64 and C-contiguous, to
        read, valid until the next iteration and not to be written (a reused buffer, or a
        view of the stored numbers)."""
        return as_float64_chunks(self.chunks(h, chunk), min(chunk, self.shape[1]))

    def step_rows(self, h: int, chunk: int, out: np.ndarray | None = None):
        """Step ``h``'s rows ``(K, ...)`` whole, in float64 (written into ``out``, a reused
        buffer, when given and of the right shape), or sparse rows for a sparse field."""
        shape = self.shape[1:]
        if out is None or out.shape != shape or out.dtype != np.float64:
            out = np.empty(shape)
        for s in range(0, shape[0], chunk):
            e = min(shape[0], s + chunk)
            out[s:e] = self.read(h, s, e)
        return out

    def times(self, h: int, z: np.ndarray, chunk: int) -> np.ndarray:
        """``Phi_h @ z`` (``(K,)`` or ``(K, m)``, float64), by chunk."""
        out = np.empty((self.shape[1],) + z.shape[1:])
        for s, e, rows in self.float64_chunks(h, chunk):
            out[s:e] = rows @ z
        return out

    def float64_array(self) -> np.ndarray | None:
        """The whole field as a C-contiguous float64 ndarray held in memory (so that steps
        can be pooled as views), or None."""
        return None

    def products(self, h: int, cols, weights=None, with_gram: bool = True):
        """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` formed where the numbers
        are (the Dask workers), or None: the caller sums the chunks it reads itself."""
        return None

    def bounds(self) -> tuple[float, float]:
        """``(min, max)`` of every number of the field (finite, checked by the caller)."""
        low, high = np.inf, -np.inf
        for h in range(self.shape[0]):
            low, high = widen_range((low, high), self.read(h))
        return float(low), float(high)

    def nonnegative(self, chunk: int) -> bool:
        """Whether every number of the field is ``>= 0`` (read by chunk)."""
        return all(bool((rows >= 0).all()) for h in range(self.shape[0])
                   for _, _, rows in self.chunks(h, chunk))

    def remote_next_values(self, nxt, h: int, qmax):
        """``V_{h+1}`` of the next-state form ``nxt`` (whose features this field holds)
        computed where the numbers are (the Dask workers), or None: read by chunk."""
        return None


def readonly(a):
    """A read-only view of the ndarray ``a`` (anything else, e.g. a Dask array, as it is)."""
    if not isinstance(a, np.ndarray):
        return a  # a Dask array: immutable already
    v = a.view()
    v.flags.writeable = False
    return v
