"""Next-state forms: where the next-state features come from (stored, a table of a finite
MDP, a feature map of stored observations); the engine asks only for values."""

from __future__ import annotations

import numpy as np

from ._finite import (
    NonFiniteRows,
    Origin,
    array_origin,
    first_nonfinite,
    nonfinite_error,
)
from .fields import Field, _as_float64
from .memory import ArrayField


class NextStates:
    """Where the next-state features come from; the engine only asks for values."""

    n_actions: int
    nonnegative: bool | None = None  # every used next-state feature >= 0 (None: unknown)
    has_known_values: bool = False

    def features(self, h, start=0, stop=None) -> np.ndarray:
        """Features of every action at the next states ``(n, A, d)`` (float64 or float32)."""
        raise NotImplementedError

    def known(self, h, start=0, stop=None):
        """Known next-state action values ``(n, A)`` (NaN: learn), or None."""
        return None

    def all_features(self, horizon: int) -> np.ndarray:
        """Every step's next-state features, trajectory-major ``(K, H, A, d)``: a view where
        they are stored, else computed (and so materialized)."""
        return np.stack([self.features(h) for h in range(horizon)], axis=1)

    def pooled_view(self, n: int):
        """``(features (n, A, d), known (n, A) or None)`` of the first ``n`` step-major samples
        as views of float64 arrays held in memory (pooled steps without a copy), or None."""
        return None

    def find_nonnegative(self, horizon: int, n: int, chunk: int) -> bool:
        """Whether every used next-state feature (steps 0 to H-2) is ``>= 0``, read by
        chunk (:attr:`nonnegative` when known)."""
        return all(bool((self.features(h, s, min(s + chunk, n)) >= 0).all())
                   for h in range(horizon - 1) for s in range(0, n, chunk))

    def values(self, h, qmax, n, chunk, out=None) -> np.ndarray:
        """``V_{h+1}`` at the K next states: ``qmax(features, known, nonneg) -> (n,)`` by chunk,
        written into ``out (n,)`` when given (returned)."""
        out = np.empty(n) if out is None else out
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            feats = _as_float64(self.features(h, s, e))
            out[s:e] = self._chunk_values(h, s, e, feats, qmax)
        return out

    def _chunk_values(self, h, s, e, feats, qmax) -> np.ndarray:
        """``qmax`` at the float64 features ``(n, A, d)`` of samples ``s:e`` of step ``h``."""
        nonneg = self.nonnegative
        if nonneg is None:
            nonneg = bool((feats >= 0).all())
        try:
            return qmax(feats, self.known(h, s, e), nonneg)
        except NonFiniteRows as exc:
            raise self.nonfinite(h, s, exc) from None

    # ------------------------------------------------------------------ errors
    def origin(self, known: bool = False) -> Origin:
        """Where the next-state features (or, ``known``, the known values) come from."""
        return array_origin("next_values" if known else "next_phi")

    def nonfinite(self, h, s, exc: NonFiniteRows) -> ValueError:
        """The error for ``exc`` (raised on the chunk of samples from ``s`` of step ``h``)."""
        i, a = exc.index[:2]
        j = exc.index[2] if len(exc.index) > 2 else None
        return nonfinite_error(self.origin(exc.known), h, s + i, exc.value, action=a, feature=j)

    def take(self, idx) -> NextStates:
        raise NotImplementedError


def linear_values(chunks, u, upper, out, check=False) -> np.ndarray:
    """``V = clip(max_a phi_a^T u, 0, upper)`` into ``out (n,)`` from ``(start, stop, rows
    (e - s, A, d) float64)`` chunks: one matrix-vector product per chunk, the max over actions
    into ``out``, one clip at the end (the same numbers as clipping each ``Q``: ``clip`` is
    monotone). With ``check``, a non-finite feature (whose product is non-finite, before the
    clip would hide an infinity) raises :class:`NonFiniteRows` indexed from ``out``'s start."""
    q = None
    for s, e, rows in chunks:
        A, d = rows.shape[1:]
        if q is None or q.size < (e - s) * A:
            q = np.empty((e - s) * A)
        qa = np.matmul(rows.reshape(-1, d), u, out=q[: (e - s) * A]).reshape(e - s, A)
        if check and not np.isfinite(np.add.reduce(q[: (e - s) * A])):
            hit = first_nonfinite(rows)
            if hit is not None:
                (i, *rest), value = hit
                raise NonFiniteRows((s + i, *rest), value)
        if A == 1:
            out[s:e] = qa[:, 0]
        elif A == 2:
            np.maximum(qa[:, 0], qa[:, 1], out=out[s:e])
        else:
            np.max(qa, axis=1, out=out[s:e])
    np.clip(out, 0.0, upper, out=out)
    return out


class StoredNext(NextStates):
    """Stored next-state features ``(H, K, A, d)`` and optional known values ``(H, K, A)``."""

    def __init__(self, next_phi: Field, next_values: Field | None = None, nonnegative=None):
        self.next_phi, self.next_values = next_phi, next_values
        self.n_actions = next_phi.shape[2]
        self.nonnegative = nonnegative
        self.has_known_values = next_values is not None

    def origin(self, known=False):
        return (self.next_values.origin("next_values") if known
                else self.next_phi.origin("next_phi"))

    def features(self, h, start=0, stop=None):
        return self.next_phi.read(h, start, stop)

    def all_features(self, horizon):
        return self.next_phi.lazy().swapaxes(0, 1)

    def pooled_view(self, n):
        feats = self.next_phi.float64_array()
        if feats is None:
            return None
        H, K = feats.shape[:2]
        known = None
        if self.next_values is not None:
            known = np.asarray(self.next_values.lazy(), dtype=float).reshape(H * K, -1)[:n]
        return feats.reshape((H * K,) + feats.shape[2:])[:n], known

    def known(self, h, start=0, stop=None):
        return None if self.next_values is None else _as_float64(
            self.next_values.read(h, start, stop))

    def values(self, h, qmax, n, chunk, out=None):
        field = self.next_phi
        v = field.remote_next_values(self, h, qmax)  # Dask: on the workers
        if v is not None:
            if out is None:
                return v
            out[...] = v
            return out
        # Chunks in float64 (reused buffers, or views of the stored numbers): no fresh
        # allocation, so no page faults, per chunk.
        out = np.empty(n) if out is None else out
        lin = self.linear_form(qmax)
        if lin is not None:
            try:
                return linear_values(field.float64_chunks(h, chunk), *lin, out,
                                     getattr(qmax, "check", False))
            except NonFiniteRows as exc:
                raise self.nonfinite(h, 0, exc) from None
        for s, e, feats in field.float64_chunks(h, chunk):
            out[s:e] = self._chunk_values(h, s, e, feats, qmax)
        return out

    def linear_form(self, qmax):
        """``(u, upper)`` when ``V = clip(max_a phi_a^T u, 0, upper)`` here (the rule's
        ``qmax.linear``: no known values, no penalty or the l1 penalty on features known to be
        non-negative), else None."""
        linear = getattr(qmax, "linear", None)
        if linear is None or self.next_values is not None or self.nonnegative is None:
            return None
        return linear(self.nonnegative)

    def take(self, idx):
        nv = None if self.next_values is None else self.next_values.subset(idx, "next_values")
        return StoredNext(self.next_phi.subset(idx, "next_phi"), nv, self.nonnegative)


class TableNext(NextStates):
    """Next-state indices ``(H, K)`` into a feature table (finite MDPs): nothing per sample.

    ``table`` is ``(S, A, d)``, or ``(H, S, A, d)`` with row ``h`` the features of the next
    states of step ``h``; ``known_table (S, A)`` gives known values by next state. ``V_{h+1}``
    is computed once per state and gathered by index (when ``S <= K``).
    """

    def __init__(self, index: Field, table: np.ndarray, known_table: np.ndarray | None = None,
                 origins: dict | None = None):
        self.index, self.table, self.known_table = index, table, known_table
        # where "next_table" and "next_table_values" came from (files: named by errors)
        self.origins = dict(origins or {})
        self.n_actions = table.shape[-2]
        used = table if table.ndim == 3 else table[: max(index.shape[0] - 1, 1)]
        self.nonnegative = bool((used >= 0).all())
        self.has_known_values = known_table is not None

    def _table(self, h):
        return self.table if self.table.ndim == 3 else self.table[h]

    def _index(self, h, start, stop, rows=None):
        """Next-state indices of samples ``start:stop`` of step ``h``, each checked to be a
        state of the table (a damaged index file is an error, never another state's row)."""
        idx = self.index.read(h, start, stop) if rows is None else rows
        S = self.table.shape[-3]
        if idx.size and (idx.min() < 0 or idx.max() >= S):
            k = start + int(np.flatnonzero((idx < 0) | (idx >= S))[0])
            raise ValueError(f"next_index[h={h}, k={k}] = {int(idx[k - start])} is not a "
                             f"state of the {S}-state next-state table: the dataset is "
                             "damaged")
        return idx

    def features(self, h, start=0, stop=None):
        return self._table(h)[self._index(h, start, stop)]

    def known(self, h, start=0, stop=None):
        if self.known_table is None:
            return None
        return self.known_table[self._index(h, start, stop)]

    def origin(self, known=False):
        name = "next_table_values" if known else "next_table"
        return self.origins.get(name) or array_origin(name)

    def nonfinite(self, h, s, exc):
        """Entry ``exc.index`` of the table (``s`` is None) or of the samples from ``s``."""
        if s is not None:  # a sample's row: name the table's entry
            state = int(np.asarray(self.index.read(h, s + exc.index[0], s + exc.index[0] + 1))[0])
            exc = NonFiniteRows((state,) + exc.index[1:], exc.value, exc.known)
        i, a = exc.index[:2]
        idx = list(exc.index) if self.table.ndim == 3 or exc.known else [h] + list(exc.index)
        origin = self.origin(exc.known)
        at = f" at index {idx}" if origin.file_index else ""
        what = "known value" if exc.known else f"feature {exc.index[2]}"
        return ValueError(
            f"{origin.label} holds {exc.value!r}{at} (next state {i}, action {a}, {what}; "
            f"used by step {h}): a fit uses only finite numbers. Fix: {origin.fix}")

    def values(self, h, qmax, n, chunk, out=None):
        table = _as_float64(self._table(h))
        if table.shape[0] > n:  # more states than samples: evaluate the sampled ones only
            return super().values(h, qmax, n, chunk, out)
        try:
            v_table = qmax(table, self.known_table, self.nonnegative)
        except NonFiniteRows as exc:
            raise self.nonfinite(h, None, exc) from None
        out = np.empty(n) if out is None else out
        for s, e, idx in self.index.chunks(h, chunk):
            np.take(v_table, self._index(h, s, e, idx), out=out[s:e])
        return out

    def take(self, idx):
        return TableNext(ArrayField(self.index.take(idx)), self.table, self.known_table,
                         self.origins)
