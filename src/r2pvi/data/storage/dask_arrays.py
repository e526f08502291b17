"""Dask arrays: a field held as a Dask array chunked along trajectories; the products a fit
needs are formed on the workers (only ``d x m`` sums and ``K`` values reach the client)."""

from __future__ import annotations

import numpy as np

from ._finite import NonFiniteRows, dask_origin
from .fields import CHUNK, Field, as_float64_chunks
from .memory import in_memory
from .next_states import linear_values


class DaskField(Field):
    """A field held as a Dask array ``(H, K, ...)`` chunked along trajectories."""

    storage = "dask"

    def __init__(self, array):
        self.array = array
        self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)
        self._persisted = None  # the array persisted on a distributed cluster (its client)

    def data(self):
        """The array to compute from: with a ``distributed`` client active, the array
        persisted on its workers once (the first time it is asked), so that later graphs name
        the workers' chunks instead of carrying the numbers; otherwise the array as given."""
        client = active_client()
        if client is None:
            return self.array
        if self._persisted is None or self._persisted[0] is not client:
            self._persisted = (client, client.persist(self.array))
        return self._persisted[1]

    def __getstate__(self):
        # A field travels to the workers inside the tasks that name its errors: without the
        # client and the persisted copy (neither belongs on a worker).
        state = dict(self.__dict__)
        state["_persisted"] = None
        return state

    def origin(self, name):
        return dask_origin(name)

    def read(self, h, start=0, stop=None, out=None):
        return np.asarray(self.data()[h, start:stop].compute())

    def lazy(self):
        return self.array

    def take(self, idx):
        return np.asarray(self.data()[:, np.asarray(idx)].compute())

    def subset(self, idx, name):
        return in_memory(self, idx, name)

    def lazy_step(self, h):
        """Step ``h`` as a lazy ``(K, d)`` Dask array chunked along trajectories only."""
        x = self.data()[h]
        return x.rechunk((x.chunks[0], -1))

    def chunks(self, h, chunk):
        # Dask's own chunks along trajectories, computed where the data is.
        bounds = np.cumsum((0,) + tuple(self.array.chunks[1]))
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            yield int(s), int(e), self.read(h, int(s), int(e))

    # ------------------------------------------------------------------ what a fit reads
    def step_rows(self, h, chunk, out=None):
        return np.ascontiguousarray(self.read(h), dtype=np.float64)

    def times(self, h, z, chunk):
        """``Phi_h @ z`` on the workers (one task per trajectory chunk)."""
        x = self.lazy_step(h)
        out = x.map_blocks(lambda b: _quiet_product(b, z),
                           chunks=(x.chunks[0],) + z.shape[1:], dtype=np.float64,
                           drop_axis=None if z.ndim == 2 else 1)
        return np.asarray(out.compute(), dtype=np.float64)

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


def _columns(y, chunks):
    """``y (K, m)`` as a Dask array chunked like the features: on a ``distributed`` cluster
    its chunks are scattered to the workers (the graph names them; a large graph would carry
    the numbers), otherwise the array wrapped as it is."""
    import dask.array as da

    client = active_client()
    if client is None:
        return da.from_array(y, chunks=(chunks, -1))
    bounds = np.cumsum((0,) + tuple(chunks))
    parts = [y[s:e] for s, e in zip(bounds[:-1], bounds[1:], strict=True)]
    futures = client.scatter(parts)
    return da.concatenate([da.from_delayed(f, shape=p.shape, dtype=p.dtype)
                           for f, p in zip(futures, parts, strict=True)])


def _quiet():
    """Dask's worker threads do not inherit the fit's ``np.errstate``: unchecked data may hold
    infinities, whose products (``inf * 0``) must not warn before the fit's checks name them.
    A new context each time (one ``errstate`` must not be entered by two threads at once)."""
    return np.errstate(invalid="ignore", over="ignore")


def _quiet_product(b, z):
    with _quiet():
        return np.asarray(b, dtype=np.float64) @ z


def _dask_products(field: DaskField, h, cols, weights, with_gram):
    """``(Phi_h^T W Phi_h or None, [Phi_h^T W c for c in cols])`` summed on the Dask workers.

    One task per trajectory chunk forms that chunk's products in float64 (the columns, and
    the weights ``W``, travel to the workers with the graph), Dask adds the partial sums up
    in a tree, and only the ``d x (d + m)`` sums reach the client: the step's features never
    do. Equal to the local chunked sums up to the order of the additions.
    """
    import dask.array as da

    x = field.lazy_step(h)
    K, d = x.shape
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

    def block(xb, yb):
        out = np.zeros((d, width))
        with _quiet():  # an infinity in the data is named by the client's check of the sums
            for s, e, rows in _float64_rows(xb):  # float64 sub-chunks, one reused buffer
                if with_gram:
                    xw = rows if weights is None else rows * yb[s:e, m:]
                    out[:, :d] += xw.T @ rows
                out[:, g:] += rows.T @ yb[s:e, :m]
        return out.reshape(1, d * width)

    nb = len(x.chunks[0])
    parts = da.map_blocks(block, x, _columns(y, x.chunks[0]),
                          chunks=((1,) * nb, (d * width,)), dtype=np.float64)
    total = np.asarray(parts.sum(axis=0).compute(), dtype=np.float64).reshape(d, width)
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
    persisted chunks' names, nothing of ``nxt`` (whose fields may hold their data)."""
    import dask.array as da

    feats = nxt.next_phi.data()[h]
    if nxt.nonnegative is None:  # once per dataset: it decides the linear form below
        nxt.nonnegative = nxt.next_phi.nonnegative_steps(nxt.next_phi.shape[0] - 1)
    nonneg = nxt.nonnegative
    lin = nxt.linear_form(qmax)
    if lin is not None:  # one matrix-vector product per sub-chunk, as in memory
        u, upper = lin
        check = getattr(qmax, "check", False)

        def linear_block(f, block_info=None):
            try:
                return linear_values(_float64_rows(f), u, upper, np.empty(len(f)), check)
            except NonFiniteRows as exc:
                start = 0 if block_info is None else block_info[0]["array-location"][0][0]
                raise _ChunkNonFinite(int(start), exc.index, exc.value, exc.known) from None

        return _compute_values(nxt, h, da.map_blocks(linear_block, feats, drop_axis=[1, 2],
                                                     dtype=np.float64))

    def block(f, k=None, block_info=None):
        f = np.asarray(f, dtype=np.float64)
        nn = bool((f >= 0).all()) if nonneg is None else nonneg
        try:
            with np.errstate(invalid="ignore", over="ignore"):  # not inherited from the fit
                return qmax(f, None if k is None else np.asarray(k[..., 0], dtype=np.float64),
                            nn)
        except NonFiniteRows as exc:  # the block's first trajectory, from Dask
            start = 0 if block_info is None else block_info[0]["array-location"][0][0]
            raise _ChunkNonFinite(int(start), exc.index, exc.value, exc.known) from None

    if nxt.next_values is None:
        v = da.map_blocks(block, feats, drop_axis=[1, 2], dtype=np.float64)
    else:
        kv = nxt.next_values.data()[h].rechunk((feats.chunks[0], -1))
        v = da.map_blocks(block, feats, kv[:, :, None], drop_axis=[1, 2], dtype=np.float64)
    return _compute_values(nxt, h, v)


def _float64_rows(f, size: int = CHUNK):
    """``(start, stop, rows)`` of ``f`` by ``size`` rows, in float64 (a view when ``f`` is
    C-contiguous float64, else one reused buffer). The in-memory chunk size: a buffer that
    stays in a core's L2 (8192 rows of ``A d = 60`` took the worker's task from about 5 ms to
    65 ms)."""
    n = len(f)
    return as_float64_chunks(((s, min(n, s + size), f[s:s + size]) for s in range(0, n, size)),
                             min(size, n))


def _compute_values(nxt, h, v):
    """The values ``v`` (a lazy ``(K,)`` array) computed, a chunk's non-finite entry named."""
    try:
        return np.asarray(v.compute(), dtype=np.float64)
    except _ChunkNonFinite as exc:
        raise nxt.nonfinite(h, exc.start, NonFiniteRows(exc.index, exc.value, exc.known)) \
            from None
