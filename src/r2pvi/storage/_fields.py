"""Fields: step-major arrays ``(H, K, ...)`` read by step and range of trajectories
(in memory, in a ``.npy`` file, in a Dask array, or computed by a feature map)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._io import FileFieldError, file_error
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


def npy_header(path: Path, name: str, min_ndim: int = 0,
               fortran_ok: bool = False) -> tuple[tuple, np.dtype, int]:
    """``(shape, dtype, offset of the data)`` of the ``.npy`` file of the field ``name``,
    checked: a ``.npy`` file (not empty, not an ``.npz`` or text), C-ordered (unless
    ``fortran_ok``), of real numbers (never Python objects: nothing is unpickled), with at
    least ``min_ndim`` dimensions and all the bytes its header announces. Anything else is a
    ``ValueError`` naming the file and the field."""
    def bad(problem):
        return file_error(path, name, problem + "; the dataset is damaged")

    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            head = fh.read(6)
            fh.seek(0)
            if not head:
                raise bad("is empty (0 bytes), not a .npy file")
            if head[:2] == b"PK":
                raise bad("is a zip archive (an .npz file?), not a .npy file")
            if head != b"\x93NUMPY":
                raise bad("is not a .npy file (no .npy magic string)")
            version = np.lib.format.read_magic(fh)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(fh)
            offset = fh.tell()
    except FileNotFoundError:
        raise bad("is missing") from None
    except (IsADirectoryError, PermissionError) as exc:
        raise bad(f"cannot be read ({exc.strerror})") from None
    except FileFieldError:
        raise
    except ValueError as exc:
        raise bad(f"has a damaged .npy header ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - EOFError, SyntaxError, ...: a damaged header
        raise bad(f"has a damaged .npy header ({type(exc).__name__}: {exc})") from None
    dtype = np.dtype(dtype)
    if dtype.hasobject:
        raise bad("holds Python objects (dtype object), which r2pvi never reads (no pickle)")
    if dtype.kind not in "biuf" or dtype.fields is not None:
        raise bad(f"holds {dtype} data, not real numbers")
    if fortran and len(shape) > 1 and not fortran_ok:
        raise bad("is Fortran-ordered; r2pvi writes and reads C-ordered .npy files")
    if len(shape) < min_ndim:
        raise bad(f"must have at least {min_ndim} dimensions, got shape {tuple(shape)}")
    need = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if size < need:
        raise bad(f"is truncated: {size} bytes, its header announces {need}")
    return tuple(int(x) for x in shape), dtype, offset


def load_npy(path: Path, name: str, mmap: bool = False) -> np.ndarray:
    """The whole ``.npy`` file of the field ``name`` (checked by :func:`npy_header`; either
    memory order), in memory or (``mmap=True``) memory-mapped read-only."""
    npy_header(path, name, fortran_ok=True)
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - checked above: only I/O errors remain
        raise file_error(path, name, f"cannot be read ({type(exc).__name__}: {exc})") from None


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

    def __init__(self, path, name: str | None = None):
        self.path = Path(path)
        shape, self.dtype, self.offset = npy_header(self.path, name or self.path.stem, 2)
        self.shape = shape
        self._row = int(np.prod(self.shape[2:], dtype=np.int64)) * self.dtype.itemsize
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
