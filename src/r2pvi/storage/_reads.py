"""Streaming a step of a :class:`FileField` in float64 chunks: views of memory-mapped windows
(float64 files), ``pread`` and a cast (float32 files, or where a file cannot be mapped)."""

from __future__ import annotations

import os

import numpy as np

from ._fields import FileField


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

    Measured (``benchmarks/bench_storage.py disk --keep --repeats 3 --estimators R2PVI-TV
    R2PVI-KL``, least CPU time of 3 fresh processes, the two codes in turn, load 1.2-2.1,
    2026-12-02; docs/storage.md). float32, K = 1e6, eight rounds: ``pread`` + cast against the
    cast from mapped 32 MiB windows used before, TV 1.71-2.24 s against 1.93-2.65 s (less in
    every round), KL 1.90-2.39 against 2.17-2.81, peak RSS 217 MiB against 248. Mapping and
    unmapping cost about 0.25 us per 4 KiB page, more than the copy ``pread`` makes into a
    cached buffer (one process reading 10 steps of next-state features: 0.28 s by ``pread``,
    0.44 s copied out of the map). In one process, 10 steps of next-state values (cast and
    product): 0.59 s with ``pread`` against 0.64 s from the map; ``MAP_POPULATE`` 0.85 s, 128
    MiB windows 0.70 s; the cast and product in L2-sized sub-chunks of 512-2048 rows no better,
    a mixed-type ``einsum`` 14% slower. float64, K = 5e5, four rounds: views of the map against
    a copy of each chunk out of the map (the code before), TV 0.85-1.10 s against 1.11-1.31, KL
    0.91-1.18 against 1.20-1.43 (K = 1e6, two rounds: TV 1.97-2.18 s against 2.59-2.79, KL
    2.15-2.28 against 2.77-3.09, about 1.2x one read); two rounds against ``pread`` into a
    float64 buffer, TV 0.99-1.04 against 1.04-1.19, KL 0.99-1.13 against 1.13-1.29. Earlier (the
    same data, fresh processes taken in turn): a reader thread that read and cast the next chunk
    while this one was computed cost about twice the CPU time per pass (wall time no better),
    and ``posix_fadvise(WILLNEED)`` took 10% of a TV fit's samples for pages already cached.

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
