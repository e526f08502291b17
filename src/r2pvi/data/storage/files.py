"""Dataset directory files: a field in a ``.npy`` file, read by range with ``pread`` or
streamed a step at a time in float64 chunks (views of memory-mapped windows for float64
files, ``pread`` and a cast for float32 ones)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._finite import file_origin
from .fields import Field
from .memory import in_memory
from .npy import npy_header


class FileField(Field):
    """A field in a ``.npy`` file: :meth:`read` reads a range with ``pread`` (into ``out`` or a
    fresh array); fits stream a step by chunk (``_prefetched``: ``pread`` and a cast for
    float32, views of memory-mapped windows for float64)."""

    storage = "disk"

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

    def subset(self, idx, name):
        return in_memory(self, idx, name)

    def float64_chunks(self, h, chunk):
        K = self.shape[1]
        yield from _prefetched(self, h, K, chunk, (min(chunk, K),) + self.shape[2:])

    def step_rows(self, h, chunk, out=None):
        shape = self.shape[1:]
        if out is None or out.shape != shape or out.dtype != np.float64:
            out = np.empty(shape)
        for s, e, rows in self.float64_chunks(h, chunk):
            out[s:e] = rows
        return out

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


def _prefetched(field: FileField, h, n, chunk, shape):
    """``(start, stop, rows)`` over step ``h`` with ``rows`` float64 ``(stop - start, ...)``,
    read in the calling thread in file order. A chunk is valid only during its iteration: the
    caller computes on it and keeps nothing (it is a reused buffer, overwritten by the next
    chunk, or a read-only view of the mapped file).

    Native float64 files (the data 8-byte aligned, as ``.npy`` files are): the step's bytes
    are memory-mapped a window at a time (``MAP_WINDOW`` bytes, then unmapped: the resident
    memory stays bounded whatever K) and each chunk is a view of the mapped pages, with no
    copy at all. float32 files (and float64 files that cannot be mapped or viewed): ``pread``
    of each chunk into a reused buffer in the storage type, then a cast into a reused float64
    buffer. Sequential access either way, so the kernel's read-ahead fetches pages not yet
    cached while a chunk is computed. The files must not be truncated while a fit reads them
    (the writers of this module never do: they write a new directory and rename it into
    place).

    Why: for float32 files, mapping and unmapping the pages costs more than ``pread``'s copy
    into a cached buffer; for float64 files the views save the copy. The measurements
    (``benchmarks/bench_storage.py disk``) and the alternatives that did not pay are in
    docs/architecture.md, "Storage internals".

    A view that escapes (a caller that keeps a chunk against the contract) never dangles:
    NumPy's view holds a buffer export of the ``mmap``, so ``mmap.close`` raises
    ``BufferError`` instead of unmapping; :func:`_unmap` then leaves the window mapped until
    the last view is released.
    """
    import mmap

    dt = field.dtype
    if not (dt == np.float64 and field.offset % dt.alignment == 0):  # np.float64 is native
        yield from _pread_chunks(field, h, 0, n, chunk, np.empty(shape))
        return
    fd, row = field._file(), field._row
    base = field.offset + h * field.shape[1] * row
    win = max(1, MAP_WINDOW // max(1, chunk * row)) * chunk
    count = int(np.prod(field.shape[2:], dtype=np.int64))
    ws = 0
    while ws < n:
        we = min(n, ws + win)
        start = base + ws * row
        off = start % mmap.ALLOCATIONGRANULARITY
        try:
            mm = mmap.mmap(fd, (we - ws) * row + off, access=mmap.ACCESS_READ,
                           offset=start - off)
        except (OSError, ValueError):  # not mappable (e.g. some network file systems)
            yield from _pread_chunks(field, h, ws, n, chunk, np.empty(shape))
            return
        mapped = None
        try:
            mapped = np.frombuffer(mm, dtype=dt, count=(we - ws) * count,
                                   offset=off).reshape((we - ws,) + field.shape[2:])
            for s in range(ws, we, chunk):
                e = min(we, s + chunk)
                yield s, e, mapped[s - ws: e - ws]
        finally:
            mapped = None
            _unmap(mm)
        ws = we


def _unmap(mm) -> bool:
    """Close the window ``mm``; False (and left mapped) while a view of it is alive.

    ``mmap.close`` refuses (``BufferError``) while an exported buffer exists, that is while a
    chunk yielded by :func:`_prefetched` is still referenced somewhere; the window is then
    unmapped when the last such view is released (the views hold the ``mmap`` object, whose
    deallocation unmaps it), so no array ever points at unmapped memory. This is the common
    case, not only a misuse: a caller's ``for`` variable still holds a window's last chunk
    when the generator moves on to the next window (and the step's last chunk when the pass
    ends); that window goes when the variable is rebound or released, so a pass holds at most
    two windows.
    """
    try:
        mm.close()
    except BufferError:
        return False
    return True


MAP_WINDOW = 1 << 25  # bytes of a float64 step mapped at a time by _prefetched (32 MiB)


def _pread_chunks(field: FileField, h, start, n, chunk, f64):
    """:func:`_prefetched` with ``pread`` into a reused buffer, from trajectory ``start``."""
    raw = f64 if field.dtype == np.float64 else np.empty(f64.shape, field.dtype)
    view = memoryview(raw.reshape(-1).view(np.uint8))
    fd, row = field._file(), field._row
    base = field.offset + h * field.shape[1] * row
    for s in range(start, n, chunk):
        e = min(n, s + chunk)
        nbytes = (e - s) * row
        if os.preadv(fd, [view[:nbytes]], base + s * row) != nbytes:
            field.read(h, s, e, out=raw[: e - s])  # a short read: the careful loop
        if raw is not f64:
            np.copyto(f64[: e - s], raw[: e - s])
        yield s, e, f64[: e - s]
