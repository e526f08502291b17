"""Dask arrays: a field held as a Dask array chunked along trajectories; the products a fit
needs are formed on the workers (only ``d x m`` sums and ``K`` values reach the client).

A fit's step costs two round trips to the workers (the next-state values, then the
products of the rule's columns, which are scattered in between), each one task per
trajectory chunk (:mod:`.dask_tasks`); the rewards of many steps come back in one.
"""

from __future__ import annotations

import numpy as np

from ._finite import NonFiniteRows, dask_origin
from .dask_tasks import active_client, flat_keys, float64_rows, map_chunks, quiet, scatter_parts
from .fields import Field
from .memory import in_memory
from .next_states import linear_values

#: Bytes of one number per step and trajectory (rewards) read in one compute.
READ_AHEAD_BYTES = 128 * 2**20


class DaskField(Field):
    """A field held as a Dask array ``(H, K, ...)`` chunked along trajectories (one step per
    chunk along the first axis, one chunk along the others: see ``from_dask``)."""

    storage = "dask"

    def __init__(self, array):
        self.array = array
        self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)
        # on a distributed cluster: (client, persisted array, its chunks' futures by key)
        self._persisted = None
        self._placement = None  # (persisted array, the worker of each step's chunks)
        self._block = None  # steps read ahead (see _read_block)

    def data(self):
        """The array to compute from: with a ``distributed`` client active, the array
        persisted on its workers once (the first time it is asked), so that later tasks name
        the workers' chunks instead of carrying the numbers; otherwise the array as given."""
        client = active_client()
        if client is None:
            return self.array
        if self._persisted is None or self._persisted[0] is not client:
            arr = client.persist(self.array)
            self._persisted = (client, arr, {f.key: f for f in client.futures_of(arr)})
        return self._persisted[1]

    def __getstate__(self):
        # A field travels to the workers inside the tasks that name its errors: without the
        # client, the persisted copy and what was read (none of them belongs on a worker).
        state = dict(self.__dict__)
        state["_persisted"] = state["_placement"] = state["_block"] = None
        return state

    def origin(self, name):
        return dask_origin(name)

    def bounds_of_chunks(self) -> np.ndarray:
        """The trajectory chunks' boundaries ``(0, k_1, ..., K)``."""
        return np.cumsum((0,) + tuple(self.array.chunks[1]))

    def step_chunks(self, h) -> list:
        """Step ``h``'s trajectory chunks in order, each ``(1, k, ...)``: the futures of the
        persisted chunks on a ``distributed`` cluster, else the array's delayed blocks."""
        arr = self.data()
        if active_client() is not None:
            futures = self._persisted[2]
            return [futures[k] for k in flat_keys(arr.__dask_keys__()[h])]
        return list(arr[h:h + 1].to_delayed().ravel())

    def placement(self, h) -> list | None:
        """The worker holding each trajectory chunk of step ``h`` on a ``distributed``
        cluster, or None (no cluster, or a chunk held nowhere): asked of the scheduler once
        per persisted array, for every step, when the persist has finished (a stale answer
        only moves columns between workers)."""
        client = active_client()
        if client is None:
            return None
        arr = self.data()
        if self._placement is None or self._placement[0] is not arr:
            from distributed import wait

            wait(list(self._persisted[2].values()))  # held once persisted (a fit needs them)
            keys = [list(flat_keys(step)) for step in arr.__dask_keys__()]
            futures = self._persisted[2]
            owners = client.who_has([futures[k] for step in keys for k in step])
            where = [[min(owners[k]) if owners.get(k) else None for k in step]
                     for step in keys]
            self._placement = (arr, where)
        where = self._placement[1][h]
        return None if any(w is None for w in where) else where

    def read(self, h, start=0, stop=None, out=None):
        if self.array.ndim == 2 and start == 0 and stop is None:
            return self._read_block(h)
        return np.asarray(self.data()[h, start:stop].compute())

    def _read_block(self, h):
        """Step ``h`` of a field of one number per step and trajectory (the rewards), read
        with its neighbours: the steps ``[b, b + n)`` holding ``h`` (``n`` steps of
        :data:`READ_AHEAD_BYTES`, blocks aligned at multiples of ``n``) come back in one
        compute and are kept until each of them has been read once (a fit reads every step
        once, backwards): one round trip for many steps (40 ms each at K = 1e6 here)."""
        block = self._block
        if block is None or block[0] is not self.data() or not block[1] <= h < block[2]:
            n = max(1, READ_AHEAD_BYTES // max(1, self.shape[1] * self.dtype.itemsize))
            lo = h - h % n
            hi = min(self.shape[0], lo + n)
            block = self._block = [self.data(), lo, hi,
                                   np.asarray(self.data()[lo:hi].compute()), set()]
        row = block[3][h - block[1]]
        block[4].add(h)
        if len(block[4]) == block[2] - block[1]:
            self._block = None
        return row

    def lazy(self):
        return self.array

    def take(self, idx):
        return np.asarray(self.data()[:, np.asarray(idx)].compute())

    def subset(self, idx, name):
        return in_memory(self, idx, name)

    def chunks(self, h, chunk):
        # Dask's own chunks along trajectories, computed where the data is.
        bounds = self.bounds_of_chunks()
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            yield int(s), int(e), self.read(h, int(s), int(e))

    # ------------------------------------------------------------------ what a fit reads
    def step_rows(self, h, chunk, out=None):
        return np.ascontiguousarray(self.read(h), dtype=np.float64)

    def times(self, h, z, chunk):
        """``Phi_h @ z`` on the workers (one task per trajectory chunk)."""
        def product(c):
            with quiet():
                return np.asarray(c[0], dtype=np.float64) @ z

        return np.concatenate(map_chunks(self.step_chunks(h), product), axis=0)

    def products(self, h, cols, weights=None, with_gram=True):
        return _dask_products(self, h, cols, weights, with_gram)

    def bounds(self):
        import dask

        a = self.data()
        low, high = dask.compute(a.min(), a.max())
        return float(low), float(high)

    def remote_next_values(self, nxt, h, qmax):
        return _dask_values(nxt, h, qmax)

    def nonnegative_steps(self, stop: int) -> bool:
        """Whether every entry of the first ``stop`` steps is ``>= 0`` (one reduction on the
        workers; NaN counts as negative)."""
        return bool((self.data()[:stop] >= 0).all().compute())


def _dask_products(field: DaskField, h, cols, weights, with_gram):
    """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` summed on the Dask workers.

    One task per trajectory chunk forms that chunk's products in float64 (the columns and
    the weights ``W`` are scattered to the workers once, by chunk), and only each chunk's
    ``d x (d + m)`` sums reach the client, which adds them up: the step's features never
    do. Equal to the local chunked sums up to the order of the additions.
    """
    K, d = field.shape[1], field.shape[2]
    cols = [np.asarray(c, dtype=np.float64) for c in cols]
    widths = [1 if c.ndim == 1 else int(np.prod(c.shape[1:])) for c in cols]
    m = sum(widths)
    y = np.empty((K, m + (0 if weights is None else 1)))
    if m:
        y[:, :m] = np.column_stack([c.reshape(K, -1) for c in cols])
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        y[:, :m] *= w[:, None]
        y[:, m] = w
    g = d if with_gram else 0
    width = g + m

    def block(chunk, yb):
        out = np.zeros((d, width))
        with quiet():  # an infinity in the data is named by the client's check of the sums
            for s, e, rows in float64_rows(chunk[0]):  # float64 sub-chunks, one buffer
                if with_gram:
                    xw = rows if weights is None else rows * yb[s:e, m:]
                    out[:, :d] += xw.T @ rows
                out[:, g:] += rows.T @ yb[s:e, :m]
        return out

    parts = scatter_parts(y, field.bounds_of_chunks(), field.placement(h))
    total = np.add.reduce(map_chunks(field.step_chunks(h), block, parts), axis=0)
    gram = total[:, :d].copy() if with_gram else None
    out, at = [], g
    for c, k in zip(cols, widths, strict=True):
        piece = total[:, at:at + k]
        out.append(piece[:, 0].copy() if c.ndim == 1 else piece.reshape((d,) + c.shape[1:]))
        at += k
    return gram, out


class _ChunkNonFinite(Exception):
    """A worker's :class:`NonFiniteRows` with the chunk's first trajectory: plain arguments,
    so that it travels back to the client, which names the entry."""

    def __init__(self, start, index, value, known):
        super().__init__(start, index, value, known)
        self.start, self.index, self.value, self.known = start, index, value, known


def _dask_values(nxt, h, qmax):
    """Next-state values of a :class:`~.next_states.StoredNext` over a Dask field computed on
    the Dask workers, one task per trajectory chunk. The tasks carry ``qmax`` and the
    chunk's first trajectory, nothing of ``nxt`` (whose fields may hold their data)."""
    field = nxt.next_phi
    if nxt.nonnegative is None:  # once per dataset: it decides the linear form below
        nxt.nonnegative = field.nonnegative_steps(field.shape[0] - 1)
    nonneg = nxt.nonnegative
    starts = [int(s) for s in field.bounds_of_chunks()[:-1]]
    lin = nxt.linear_form(qmax)
    if lin is not None:  # one matrix-vector product per sub-chunk, as in memory
        u, upper = lin
        check = getattr(qmax, "check", False)

        def linear_block(chunk, start):
            f = chunk[0]
            try:
                return linear_values(float64_rows(f), u, upper, np.empty(len(f)), check)
            except NonFiniteRows as exc:
                raise _ChunkNonFinite(start, exc.index, exc.value, exc.known) from None

        return _gather_values(nxt, h, field.step_chunks(h), linear_block, starts)

    def block(chunk, start, k=None):
        f = np.asarray(chunk[0], dtype=np.float64)
        nn = bool((f >= 0).all()) if nonneg is None else nonneg
        try:
            with quiet():  # not inherited from the fit
                return qmax(f, None if k is None else np.asarray(k[0], dtype=np.float64), nn)
        except NonFiniteRows as exc:  # the chunk's first trajectory
            raise _ChunkNonFinite(start, exc.index, exc.value, exc.known) from None

    known = [] if nxt.next_values is None else [nxt.next_values.step_chunks(h)]
    return _gather_values(nxt, h, field.step_chunks(h), block, starts, *known)


def _gather_values(nxt, h, chunks, fn, *args):
    """The values ``fn`` computes on each chunk, gathered into ``(K,)``; a chunk's
    non-finite entry named."""
    try:
        parts = map_chunks(chunks, fn, *args)
    except _ChunkNonFinite as exc:
        raise nxt.nonfinite(h, exc.start, NonFiniteRows(exc.index, exc.value, exc.known)) \
            from None
    return np.concatenate([np.asarray(p, dtype=np.float64) for p in parts])
