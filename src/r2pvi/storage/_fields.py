"""Fields: step-major arrays ``(H, K, ...)`` read by step and range of trajectories
(in memory, in a ``.npy`` file, in a Dask array, or computed by a feature map)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._finite import Origin, array_origin, dask_origin, file_origin, map_origin

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


class ArrayField(Field):
    """A field held in a NumPy array (kept as a read-only view; never copied); ``origin``
    names where its numbers came from when not the caller (rows taken from a file)."""

    def __init__(self, array: np.ndarray, origin: Origin | None = None):
        view = array.view() if isinstance(array, np.ndarray) else np.asarray(array)
        view.flags.writeable = False
        self.array = view
        self.shape, self.dtype = view.shape, view.dtype
        self._origin = origin

    def origin(self, name):
        return array_origin(name) if self._origin is None else self._origin

    def read(self, h, start=0, stop=None):
        return self.array[h, start:stop]

    def lazy(self):
        return self.array

    def take(self, idx):
        return self.array[:, idx]


class FileField(Field):
    """A field in a ``.npy`` file: :meth:`read` reads a range with ``pread`` (into ``out`` or a
    fresh array); fits stream a step by chunk (``_prefetched``: ``pread`` and a cast for
    float32, views of memory-mapped windows for float64)."""

    def __init__(self, path):
        self.path = Path(path)
        with open(self.path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            self.offset = fh.tell()
        if fortran or dtype.hasobject:
            raise ValueError(f"{self.path} is not a C-ordered numeric .npy file")
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._row = int(np.prod(self.shape[2:], dtype=np.int64)) * self.dtype.itemsize
        size = self.offset + int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize
        if os.path.getsize(self.path) < size:
            raise ValueError(f"{self.path} is truncated: expected {size} bytes")
        self._fd: int | None = None

    def origin(self, name):
        return file_origin(self.path)

    def _file(self) -> int:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY)
        return self._fd

    def read(self, h, start=0, stop=None, out=None):
        K = self.shape[1]
        stop = K if stop is None else min(stop, K)
        shape = (stop - start,) + self.shape[2:]
        if out is None or out.shape != shape or out.dtype != self.dtype:
            out = np.empty(shape, dtype=self.dtype)
        nbytes = out.nbytes
        if nbytes:
            pos = self.offset + (h * K + start) * self._row
            view = memoryview(out.reshape(-1).view(np.uint8))
            done = 0
            while done < nbytes:  # pread may return less than asked for
                got = os.preadv(self._file(), [view[done:]], pos + done)
                if got <= 0:
                    raise OSError(f"unexpected end of {self.path}")
                done += got
        return out

    def lazy(self):
        return np.load(self.path, mmap_mode="r", allow_pickle=False)

    def take(self, idx):
        return np.asarray(self.lazy()[:, idx])

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):  # pragma: no cover - interpreter shutdown
        try:
            self.close()
        except Exception:
            pass

    def __getstate__(self):  # picklable for process pools: reopen the file there
        state = dict(self.__dict__)
        state["_fd"] = None
        return state


class DaskField(Field):
    """A field held as a Dask array ``(H, K, ...)`` chunked along trajectories."""

    def __init__(self, array):
        self.array = array
        self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)

    def origin(self, name):
        return dask_origin(name)

    def read(self, h, start=0, stop=None):
        return np.asarray(self.array[h, start:stop].compute())

    def lazy(self):
        return self.array

    def take(self, idx):
        return np.asarray(self.array[:, np.asarray(idx)].compute())

    def step_rows(self, h):
        """Step ``h`` as a lazy ``(K, d)`` Dask array chunked along trajectories only."""
        x = self.array[h]
        return x.rechunk((x.chunks[0], -1))

    def chunks(self, h, chunk):
        # Dask's own chunks along trajectories, computed where the data is.
        bounds = np.cumsum((0,) + tuple(self.array.chunks[1]))
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            yield int(s), int(e), self.read(h, int(s), int(e))


class MappedField(Field):
    """Taken-action features computed from stored observations and actions by a feature map:
    ``read(h, s, e) = feature_map(observations[h, s:e], actions[h, s:e])`` ``(n, d)``."""

    def __init__(self, observations: Field, actions: Field, feature_map, n_features: int):
        self.observations, self.actions, self.feature_map = observations, actions, feature_map
        H, K = observations.shape[:2]
        self.shape, self.dtype = (H, K, int(n_features)), np.dtype(np.float64)

    def origin(self, name):
        return map_origin("taken-action features")

    def read(self, h, start=0, stop=None):
        obs = self.observations.read(h, start, stop)
        act = np.asarray(self.actions.read(h, start, stop), dtype=np.int64)
        out = np.asarray(self.feature_map(obs, act), dtype=np.float64)
        if out.shape != (obs.shape[0], self.shape[2]):
            raise ValueError(f"feature_map returned shape {out.shape} for {obs.shape[0]} "
                             f"observations; expected (n, d) = ({obs.shape[0]}, {self.shape[2]})")
        return out

    def lazy(self):
        return np.stack([self.read(h) for h in range(self.shape[0])])

    def take(self, idx):
        return self.lazy()[:, idx]
