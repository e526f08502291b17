"""Sparse rows: features held as one CSR matrix per step (tile coding, aggregation, one-hot).

Feature maps such as tile coding have tens of thousands of features but only a handful of
non-zeros per row. A :class:`SparseRowsField` keeps each step's taken-action rows as a CSR
matrix ``(K, d)``, a :class:`SparseNext` each step's next-state rows as a
:class:`StackedSparse` ``(K, A, d)`` (row ``tau * A + a``): a fit reads a step's rows whole
as CSR and never densifies one (the Gram matrix, the regressions, the next-state values and
the penalties are sparse products; see :class:`~r2pvi.duals.GramFactor`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from .fields import Field, _as_float64
from .next_states import NextStates

__all__ = ["StackedSparse", "SparseRowsField", "SparseNext", "stack_rows", "flat_rows"]


class StackedSparse:
    """Sparse rows of features ``(*lead, d)`` stored as one CSR matrix ``(prod(lead), d)``.

    The engine's next-state features are ``(K, A, d)``; scipy.sparse matrices are 2-D, so the
    leading shape travels with the matrix (row ``tau * A + a``).
    """

    __slots__ = ("matrix", "lead")

    def __init__(self, matrix, lead: tuple[int, ...]):
        self.matrix = sp.csr_matrix(matrix)
        self.lead = tuple(int(x) for x in lead)
        if int(np.prod(self.lead)) != self.matrix.shape[0]:
            raise ValueError(f"{self.matrix.shape[0]} rows cannot have leading shape {lead}")

    @property
    def shape(self) -> tuple[int, ...]:
        return self.lead + (self.matrix.shape[1],)


def stack_rows(parts: Sequence):
    """Concatenate feature rows along the first axis: arrays, CSR matrices or StackedSparse."""
    first = parts[0]
    if isinstance(first, StackedSparse):
        lead = (sum(p.lead[0] for p in parts),) + first.lead[1:]
        return StackedSparse(sp.vstack([p.matrix for p in parts], format="csr"), lead)
    if sp.issparse(first):
        return sp.vstack(parts, format="csr")
    return np.concatenate(parts)


def flat_rows(phi):
    """``(flat (m, d), lead)`` of features ``phi (..., d)``: dense, or stacked sparse rows."""
    if isinstance(phi, StackedSparse):
        return phi.matrix, phi.lead
    return phi.reshape(-1, phi.shape[-1]), phi.shape[:-1]


class SparseRowsField(Field):
    """Taken-action features as H CSR matrices ``(K, d)`` (float64), one per step.

    :meth:`step_rows` gives a step's CSR matrix itself; reads of a range of trajectories are
    CSR rows too. There is no dense view (:meth:`lazy` refuses: it would densify the rows).
    """

    storage = "memory (sparse rows)"
    dense_rows = False

    def __init__(self, steps: Sequence):
        self.steps = list(steps)
        K, d = self.steps[0].shape
        self.shape, self.dtype = (len(self.steps), K, d), np.dtype(np.float64)

    def read(self, h, start=0, stop=None, out=None):
        return self.steps[h][start:stop]

    def lazy(self):
        raise TypeError("a dataset of sparse rows has no dense phi; use step(h)[0] (sparse rows, "
                        "CSR) or step_times(h, z)")

    def take(self, idx):
        raise TypeError("sparse rows are taken with subset(idx), not as a dense array")

    def subset(self, idx, name):
        return SparseRowsField([m[idx] for m in self.steps])

    def float64_chunks(self, h, chunk):
        K = self.shape[1]
        for s in range(0, K, chunk):
            yield s, min(K, s + chunk), self.steps[h][s:s + chunk]

    def step_rows(self, h, chunk, out=None):
        return self.steps[h]

    def times(self, h, z, chunk):
        return np.asarray(self.steps[h] @ z, dtype=np.float64)

    def bounds(self):
        low = min(float(m.min()) for m in self.steps)
        high = max(float(m.max()) for m in self.steps)
        return low, high

    def nonnegative(self, chunk):
        return all(bool((m.data >= 0).all()) for m in self.steps)

    def describe(self):
        return f", sparse rows, nnz(phi)={sum(m.nnz for m in self.steps)}"


class SparseNext(NextStates):
    """Next-state features as H :class:`StackedSparse` ``(K, A, d)`` (row ``tau * A + a``),
    known values ``(H, K, A)`` as a field (NaN: learn) or None.

    ``V_{h+1}`` is computed on a step's rows whole (sparse products, no chunking):
    :meth:`features` of a whole step is the stored :class:`StackedSparse` itself.
    """

    def __init__(self, steps: Sequence, next_values: Field | None = None):
        self.steps = list(steps)
        self.n_actions = self.steps[0].lead[1]
        self.next_values = next_values
        self.has_known_values = next_values is not None
        # every stored next-state entry, the last step's included (its rows are never used)
        self.nonnegative = all(bool((m.matrix.data >= 0).all()) for m in self.steps)

    def features(self, h, start=0, stop=None):
        m = self.steps[h]
        K, A = m.lead
        if start == 0 and (stop is None or stop >= K):
            return m
        stop = K if stop is None else min(stop, K)
        return StackedSparse(m.matrix[start * A:stop * A], (stop - start, A))

    def known(self, h, start=0, stop=None):
        return None if self.next_values is None else _as_float64(
            self.next_values.read(h, start, stop))

    def all_features(self, horizon):
        raise TypeError("a dataset of sparse rows has no dense next_phi; use step(h)[2] "
                        "(StackedSparse (K, A, d))")

    def find_nonnegative(self, horizon, n, chunk):
        return self.nonnegative

    def values(self, h, qmax, n, chunk, out=None):
        v = qmax(self.features(h), self.known(h), self.nonnegative)
        if out is None:
            return v
        out[...] = v
        return out

    def take(self, idx):
        idx = np.asarray(idx)
        A = self.n_actions
        rows = (idx[:, None] * A + np.arange(A)[None, :]).ravel()
        nv = None if self.next_values is None else self.next_values.subset(idx, "next_values")
        return SparseNext([StackedSparse(m.matrix[rows], (idx.size, A)) for m in self.steps], nv)
