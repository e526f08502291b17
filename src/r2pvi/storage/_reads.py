"""Streaming a step of a :class:`FileField` in float64 chunks: memory-mapped windows,
``pread`` where a file cannot be mapped."""

from __future__ import annotations

import os

import numpy as np

from ._fields import FileField


def _prefetched(field: FileField, h, n, chunk, shape):
    """``(start, stop, rows)`` over step ``h`` with ``rows`` float64 ``(stop - start, ...)``,
    read in the calling thread in file order. A chunk is valid only during its iteration: the
    caller computes on it and keeps nothing (for float32 files it is a reused buffer,
    overwritten by the next chunk; for native float64 files a read-only view of the mapped
    file, see below).

    The step's bytes are memory-mapped a window at a time (``MAP_WINDOW`` bytes, then
    unmapped: the resident memory stays bounded whatever K). float32 files: each chunk is cast
    from the mapped pages straight into the float64 buffer: the page cache is read once, with
    no copy into an intermediate buffer (``pread`` copies every byte once more; measured at
    K = 1e6, d = 30, A = 2, float32, in fresh processes taken in turn: R2PVI-TV 2.25-2.38 s of
    CPU against 2.46-2.65 s with ``pread``, R2PVI-KL 2.37-2.52 against 2.65-3.06). Native
    (and aligned) float64 files: each chunk is a view of the mapped pages, with no copy at all.
    The files must not be truncated while a fit reads them (the writers of this module never
    do: they write a new directory and rename it into place). Where the file cannot be
    mapped, ``pread`` into a reused buffer. Sequential access either way, so the kernel's
    read-ahead fetches pages not yet cached while a chunk is computed.

    A view that escapes (a caller that keeps a chunk against the contract) never dangles:
    NumPy's view holds a buffer export of the ``mmap``, so ``mmap.close`` raises
    ``BufferError`` instead of unmapping; :func:`_unmap` then leaves the window mapped until
    the last view is released (the ``mmap`` object unmaps when it is deallocated).

    Also measured there: a reader thread that read and cast the next chunk while this one was
    computed cost about twice the CPU time per pass (wall time no better), and asking the
    kernel to read ahead (``posix_fadvise(WILLNEED)``) took 10% of a TV fit's samples for
    pages already cached.
    """
    import mmap

    fd, row = field._file(), field._row
    zero_copy = field.dtype == np.float64  # native byte order (np.float64 is native)
    f64 = None if zero_copy else np.empty(shape)
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
            mapped = np.frombuffer(mm, dtype=field.dtype, count=(we - ws) * count,
                                   offset=off).reshape((we - ws,) + field.shape[2:])
            if zero_copy and mapped.flags.aligned:
                for s in range(ws, we, chunk):
                    yield s, min(we, s + chunk), mapped[s - ws: min(we, s + chunk) - ws]
            else:
                if f64 is None:  # float64 at an unaligned offset: copy (never seen in .npy)
                    f64 = np.empty(shape)
                for s in range(ws, we, chunk):
                    e = min(we, s + chunk)
                    np.copyto(f64[: e - s], mapped[s - ws: e - ws])
                    yield s, e, f64[: e - s]
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
    case for a step's last window: a caller's loop variable still holds the last chunk when
    the pass ends, and the window goes with that variable.
    """
    try:
        mm.close()
    except BufferError:
        return False
    return True


MAP_WINDOW = 1 << 25  # bytes of a step mapped at a time by _prefetched (32 MiB)


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
