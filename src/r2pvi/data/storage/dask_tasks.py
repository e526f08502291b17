"""Tasks on a Dask array's trajectory chunks: one task per chunk of a step, one round trip.

On a ``distributed`` cluster the tasks are submitted against the futures of the persisted
chunks (``Client.map``; no graph to build, optimize or finalize: a round trip of 8 tasks
took 20 ms here against 43 ms for the same work as a Dask-array graph) and the client
gathers their results itself. With Dask's local schedulers they are delayed calls on the
array's blocks. Columns the tasks need travel once per request, each chunk to the worker
that holds the features it multiplies (:func:`scatter_parts`).
"""

from __future__ import annotations

import numpy as np

from .fields import CHUNK, as_float64_chunks

__all__ = ["active_client", "map_chunks", "scatter_parts", "flat_keys"]


def active_client():
    """The ``distributed`` client Dask computes with, or None (Dask's local schedulers, or
    ``distributed`` not installed)."""
    try:
        from distributed import default_client
    except ImportError:  # pragma: no cover - dask without distributed
        return None
    try:
        client = default_client()
    except ValueError:  # no client
        return None
    import dask.base

    return client if dask.base.get_scheduler() == client.get else None


def map_chunks(chunks, fn, *args) -> list:
    """``[fn(chunks[j], *(a[j] for a in args)) for j]`` computed where the chunks are:
    ``chunks`` are futures (a ``distributed`` client: :meth:`Client.map`, results gathered
    by the client) or delayed blocks (Dask's local schedulers); the arguments' items are
    futures, delayed objects or small values."""
    client = active_client()
    if client is not None:
        return client.gather(client.map(fn, chunks, *args, pure=False))
    import dask

    call = dask.delayed(fn, pure=False)
    return list(dask.compute(*[call(c, *(a[j] for a in args)) for j, c in enumerate(chunks)]))


def scatter_parts(y: np.ndarray, bounds, placement=None) -> list:
    """``y``'s rows cut at ``bounds`` (the trajectory chunks), ready for :func:`map_chunks`:
    on a ``distributed`` cluster scattered once, each part to the worker that holds the
    chunk it goes with (``placement``: a worker address per chunk, or None), straight from
    the client (:func:`scatter_direct`) and without hashing the numbers for a key (a scatter
    of 24 MB: 66 ms as Dask does it by default, 20 ms so); otherwise the parts themselves."""
    parts = [y[s:e] for s, e in zip(bounds[:-1], bounds[1:], strict=True)]
    client = active_client()
    if client is None:
        return parts
    futures = [None] * len(parts)
    groups: dict = {}
    for j, where in enumerate(placement or [None] * len(parts)):
        groups.setdefault(where, []).append(j)
    direct = scatter_direct(client)
    for where, idx in groups.items():
        sent = client.scatter([parts[j] for j in idx], hash=False, direct=direct,
                              workers=None if where is None else [where])
        for j, f in zip(idx, sent, strict=True):
            futures[j] = f
    return futures


def scatter_direct(client) -> bool:
    """Whether data go from the client straight to the workers rather than through the
    scheduler: the client's own ``direct_to_workers`` when it was set, else True. A client
    that cannot reach the workers (behind some gateways) is made with
    ``Client(..., direct_to_workers=False)``."""
    direct = getattr(client, "direct_to_workers", None)
    return True if direct is None else bool(direct)


def flat_keys(keys):
    """The keys of a nested list of Dask keys, in order."""
    if isinstance(keys, list):
        for k in keys:
            yield from flat_keys(k)
    else:
        yield keys


def quiet():
    """Dask's worker threads do not inherit the fit's ``np.errstate``: unchecked data may hold
    infinities, whose products (``inf * 0``) must not warn before the fit's checks name them.
    A new context each time (one ``errstate`` must not be entered by two threads at once)."""
    return np.errstate(invalid="ignore", over="ignore")


def float64_rows(f, size: int = CHUNK):
    """``(start, stop, rows)`` of ``f`` by ``size`` rows, in float64 (a view when ``f`` is
    C-contiguous float64, else one reused buffer). The in-memory chunk size: a buffer that
    stays in a core's L2 (8192 rows of ``A d = 60`` took the worker's task from about 5 ms to
    65 ms)."""
    n = len(f)
    return as_float64_chunks(((s, min(n, s + size), f[s:s + size]) for s in range(0, n, size)),
                             min(size, n))
