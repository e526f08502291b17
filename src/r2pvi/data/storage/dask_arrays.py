"""Dask arrays: a field held as a Dask array chunked along trajectories; the products a fit
needs are formed on the workers (only ``d x m`` sums and ``K`` values reach the client)."""

from __future__ import annotations

import numpy as np

from ._finite import NonFiniteRows, dask_origin
from .fields import Field
from .memory import in_memory


class DaskField(Field):
    """A field held as a Dask array ``(H, K, ...)`` chunked along trajectories."""

    storage = "dask"

    def __init__(self, array):
        self.array = array
        self.shape, self.dtype = tuple(array.shape), np.dtype(array.dtype)

    def origin(self, name):
        return dask_origin(name)

    def read(self, h, start=0, stop=None, out=None):
        return np.asarray(self.array[h, start:stop].compute())

    def lazy(self):
        return self.array

    def take(self, idx):
        return np.asarray(self.array[:, np.asarray(idx)].compute())

    def subset(self, idx, name):
        return in_memory(self, idx, name)

    def lazy_step(self, h):
        """Step ``h`` as a lazy ``(K, d)`` Dask array chunked along trajectories only."""
        x = self.array[h]
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

        low, high = dask.compute(self.array.min(), self.array.max())
        return float(low), float(high)

    def remote_next_values(self, nxt, h, qmax):
        return _dask_values(nxt, h, qmax)


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
        xb = np.asarray(xb, dtype=np.float64)
        out = np.empty((d, width))
        with _quiet():  # an infinity in the data is named by the client's check of the sums
            if with_gram:
                xw = xb if weights is None else xb * yb[:, m:]
                out[:, :d] = xw.T @ xb
            out[:, g:] = xb.T @ yb[:, :m]
        return out.reshape(1, d * width)

    nb = len(x.chunks[0])
    parts = da.map_blocks(block, x, da.from_array(y, chunks=(x.chunks[0], -1)),
                          chunks=((1,) * nb, (d * width,)), dtype=np.float64)
    total = np.asarray(parts.sum(axis=0).compute(), dtype=np.float64).reshape(d, width)
    gram = total[:, :d].copy() if with_gram else None
    out, at = [], g
    for c, k in zip(cols, widths, strict=True):
        piece = total[:, at:at + k]
        out.append(piece[:, 0].copy() if c.ndim == 1 else piece.reshape((d,) + c.shape[1:]))
        at += k
    return gram, out


def _dask_values(nxt, h, qmax):
    """Next-state values of a :class:`~.next_states.StoredNext` over a Dask field computed on
    the Dask workers, one task per trajectory chunk."""
    import dask.array as da

    feats = nxt.next_phi.array[h]
    nonneg = nxt.nonnegative

    def block(f, k=None, block_info=None):
        f = np.asarray(f, dtype=np.float64)
        nn = bool((f >= 0).all()) if nonneg is None else nonneg
        try:
            with np.errstate(invalid="ignore", over="ignore"):  # not inherited from the fit
                return qmax(f, None if k is None else np.asarray(k[..., 0], dtype=np.float64),
                            nn)
        except NonFiniteRows as exc:  # the block's first trajectory, from Dask
            start = 0 if block_info is None else block_info[0]["array-location"][0][0]
            raise nxt.nonfinite(h, int(start), exc) from None

    if nxt.next_values is None:
        v = da.map_blocks(block, feats, drop_axis=[1, 2], dtype=np.float64)
    else:
        kv = nxt.next_values.array[h].rechunk((feats.chunks[0], -1))
        v = da.map_blocks(block, feats, kv[:, :, None], drop_axis=[1, 2], dtype=np.float64)
    return np.asarray(v.compute(), dtype=np.float64)
