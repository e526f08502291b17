"""State features: ``psi(s)`` stored once per observation, actions by index.

A feature map crossed with discrete actions, ``phi(s, a) = e_a (x) psi(s)``
(:func:`r2pvi.features.cross_actions`), has ``d = A m`` features of which only the ``m`` of
the taken action are non-zero. Storing ``phi`` for the taken action and for every action at
the next state costs ``(1 + A) d = (1 + A) A m`` numbers per transition; this kind stores
``psi`` of each observation once (``T + 1`` rows per episode: an observation is the next
state of one step and the state of the following one) and the actions as indices, ``m``
numbers per transition, in float32 or float64:

- ``psi (H+1, K, m)``: row ``h`` holds the observation of step ``h`` of each episode;
- ``actions (H, K)``: the taken action's index, ``-1`` where a step carries no data (after
  an episode's end). A row with ``-1`` is a zero feature row: it adds nothing to a Gram
  matrix or a regression, whatever ``psi`` holds there.

:class:`CrossedField` (taken-action rows) and :class:`CrossedNext` (next-state rows) give
every read of the field protocol by crossing a chunk at a time; :class:`CrossedRows` is the
pooled steps' rows as one linear map, whose products (the Gram matrix, ``Phi^T W y``,
``Q(s', .) = psi(s') W``) read ``psi`` once, in chunks converted to float64: sums are
accumulated in float64 whatever the storage type.
"""

from __future__ import annotations

import numpy as np

from ._finite import map_origin
from .fields import CHUNK, Field, as_float64_chunks
from .next_states import NextStates

__all__ = ["CrossedRows", "CrossedField", "CrossedNext", "cross_rows"]


def cross_rows(psi: np.ndarray, actions: np.ndarray | None, n_actions: int,
               dtype=np.float64) -> np.ndarray:
    """``e_a (x) psi`` as dense rows: ``(n, A m)`` for ``actions (n,)`` (``-1``: a zero row),
    or every action ``(n, A, A m)`` when ``actions`` is None.

    >>> cross_rows(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([1, -1]), 2).tolist()
    [[0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 0.0]]
    """
    n, m = psi.shape
    A = int(n_actions)
    if actions is None:
        out = np.zeros((n, A, A * m), dtype=dtype)
        for a in range(A):
            out[:, a, a * m:(a + 1) * m] = psi
        return out
    out = np.zeros((n, A * m), dtype=dtype)
    for a in range(A):
        rows = actions == a
        out[rows, a * m:(a + 1) * m] = psi[rows]
    return out


class CrossedRows:
    """Rows ``phi(s, a) = e_a (x) psi(s)`` of ``n`` samples as a linear map, never formed.

    Parameters
    ----------
    psi : ndarray (n, m)
        State features (float32 or float64; read in float64 chunks).
    actions : ndarray (n,) or None
        The taken actions (``-1``: an empty row): taken-action rows ``(n, d)``. None: the
        rows of every action at each sample, ``(n, A, d)`` (next states).
    n_actions : int

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> psi, acts = rng.random((7, 3)), np.array([0, 1, 1, -1, 0, 1, 0])
    >>> rows, dense = CrossedRows(psi, acts, 2), cross_rows(psi, acts, 2)
    >>> y = rng.random(7)
    >>> bool(np.allclose(rows.rmatmul(y), dense.T @ y))
    True
    >>> bool(np.allclose(rows.gram(), dense.T @ dense))
    True
    """

    def __init__(self, psi: np.ndarray, actions: np.ndarray | None, n_actions: int,
                 chunk: int = CHUNK):
        self.psi, self.actions = psi, actions
        self.n_actions = int(n_actions)
        self.n, self.m = psi.shape
        self.chunk = int(chunk)
        self._hot = None  # the actions one-hot (n, A), formed by the first regression

    @property
    def shape(self) -> tuple[int, ...]:
        d = self.n_actions * self.m
        return (self.n, d) if self.actions is not None else (self.n, self.n_actions, d)

    def chunks(self):
        """``(start, stop, psi (stop - start, m))`` in float64 (a view, or a reused buffer)."""
        n, c = self.n, self.chunk
        return as_float64_chunks(((s, min(n, s + c), self.psi[s:s + c])
                                  for s in range(0, n, c)), min(c, n))

    def dense(self) -> np.ndarray:
        """The rows as a float64 array ``(n, d)`` (or ``(n, A, d)``)."""
        out = np.empty(self.shape)
        for s, e, rows in self.chunks():
            out[s:e] = cross_rows(rows, None if self.actions is None else self.actions[s:e],
                                  self.n_actions)
        return out

    # ------------------------------------------------------------------ taken-action rows
    def _onehot(self) -> np.ndarray:
        """``(n, A)`` float64: 1 in the column of each row's action (none for ``-1``), formed
        once (``8 A`` bytes a row)."""
        if self._hot is None:
            hot = np.zeros((self.n, self.n_actions))
            used = np.flatnonzero(self.actions >= 0)
            hot[used, self.actions[used]] = 1.0
            self._hot = hot
        return self._hot

    def rmatmul(self, y: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """``Phi^T W y`` for ``y (n,)`` -> ``(d,)`` or ``(n, k)`` -> ``(d, k)``: one read of
        ``psi`` (a product ``Y_c^T psi_c`` per chunk, ``Y_c`` the values in their action's
        column)."""
        y = np.asarray(y, dtype=float)
        if weights is not None:
            y = (y.T * weights).T
        k = 1 if y.ndim == 1 else y.shape[1]
        hot = self._onehot()
        A = self.n_actions
        acc = np.zeros((A * k, self.m))
        for s, e, rows in self.chunks():
            if y.ndim == 1:
                spread = hot[s:e] * y[s:e, None]
            else:
                spread = (hot[s:e, :, None] * y[s:e, None, :]).reshape(e - s, A * k)
            acc += spread.T @ rows
        # (A, k, m) -> (A, m, k): block a of the features is action a's
        out = acc.reshape(A, k, self.m).transpose(0, 2, 1).reshape(A * self.m, k)
        return out[:, 0].copy() if y.ndim == 1 else out

    def colsums(self, weights: np.ndarray | None = None) -> np.ndarray:
        """``Phi^T W 1 (d,)``."""
        return self.rmatmul(np.ones(self.n), weights)

    def gram(self, weights: np.ndarray | None = None) -> np.ndarray:
        """``Phi^T W Phi (d, d)``: block diagonal, one ``m x m`` block per action."""
        A, m = self.n_actions, self.m
        out = np.zeros((A * m, A * m))
        for s, e, rows in self.chunks():
            act = self.actions[s:e]
            for a in range(A):
                sel = rows[act == a]
                xw = sel if weights is None else sel * weights[s:e][act == a, None]
                out[a * m:(a + 1) * m, a * m:(a + 1) * m] += xw.T @ sel
        return out

    def nonnegative(self) -> bool:
        """Whether every row is non-negative (``psi >= 0`` wherever an action was taken)."""
        return all(bool((rows[self.actions[s:e] >= 0] >= 0).all())
                   for s, e, rows in self.chunks())

    def used(self) -> np.ndarray:
        """Which rows hold a non-zero feature (a taken action and a non-zero ``psi``)."""
        out = self.actions >= 0
        for s, e, rows in self.chunks():
            out[s:e] &= rows.any(axis=1)
        return out

    # ------------------------------------------------------------------ next-state rows
    def action_values(self, w: np.ndarray) -> np.ndarray:
        """``phi(s, a)^T w`` for every sample and action ``(n, A)``: ``psi W`` with ``W (m, A)``
        the action blocks of ``w (d,)`` (next-state rows)."""
        W = np.ascontiguousarray(np.asarray(w, dtype=float).reshape(self.n_actions, self.m).T)
        out = np.empty((self.n, self.n_actions))
        for s, e, rows in self.chunks():
            np.matmul(rows, W, out=out[s:e])
        return out

    def map_dense(self, fn) -> np.ndarray:
        """``fn(rows (n_c, A, d))`` of every chunk of the dense rows, concatenated (what is
        computed once per fit, e.g. the penalty at every next state)."""
        parts = [fn(cross_rows(rows, None, self.n_actions)) for _, _, rows in self.chunks()]
        return np.concatenate(parts) if parts else np.zeros((0, self.n_actions))


# ---------------------------------------------------------------------- fields
class CrossedField(Field):
    """Taken-action rows ``(H, K, d)`` from ``psi (H+1, K, m)`` and ``actions (H, K)``."""

    def __init__(self, psi: np.ndarray, actions: np.ndarray, n_actions: int):
        self.psi, self.actions, self.n_actions = psi, actions, int(n_actions)
        H, K = actions.shape
        self.shape = (H, K, self.n_actions * psi.shape[2])
        self.dtype = psi.dtype

    def origin(self, name):
        return map_origin("taken-action features")

    def describe(self) -> str:
        return f", state features m={self.psi.shape[2]} x {self.n_actions} actions"

    def read(self, h, start=0, stop=None, out=None):
        return cross_rows(self.psi[h, start:stop], self.actions[h, start:stop],
                          self.n_actions, self.dtype)

    def lazy(self):
        return np.stack([self.read(h) for h in range(self.shape[0])])

    def take(self, idx):
        return np.stack([self.read(h)[idx] for h in range(self.shape[0])])

    def subset(self, idx, name):
        return CrossedField(_readonly(self.psi[:, idx]), _readonly(self.actions[:, idx]),
                            self.n_actions)

    def nonnegative(self, chunk: int) -> bool:
        used = self.actions >= 0
        return bool((self.psi[:-1][used] >= 0).all())

    def crossed_step(self, h: int) -> CrossedRows:
        """Step ``h``'s rows as :class:`CrossedRows` (views): their sums without forming them
        (a fit's diagnostics)."""
        return CrossedRows(self.psi[h], self.actions[h], self.n_actions)

    def pooled_rows(self, P: int) -> CrossedRows:
        """Steps ``0 .. P-1`` as one :class:`CrossedRows` (step-major rows, a view)."""
        K, m = self.shape[1], self.psi.shape[2]
        return CrossedRows(self.psi[:P].reshape(P * K, m), self.actions[:P].reshape(P * K),
                           self.n_actions)


class CrossedNext(NextStates):
    """Next-state rows of every action: observation ``h + 1`` of ``psi (H+1, K, m)``, with
    optional known values ``(H, K, A)`` (a field)."""

    def __init__(self, psi: np.ndarray, n_actions: int, known_values: Field | None = None,
                 nonnegative: bool | None = None):
        self.psi, self.n_actions = psi, int(n_actions)
        self.next_values = known_values
        self.has_known_values = known_values is not None
        self.nonnegative = nonnegative

    def origin(self, known=False):
        if known:
            return self.next_values.origin("next_values")
        return map_origin("features of the next observations")

    def features(self, h, start=0, stop=None):
        return cross_rows(self.psi[h + 1, start:stop], None, self.n_actions, self.psi.dtype)

    def known(self, h, start=0, stop=None):
        if self.next_values is None:
            return None
        return np.asarray(self.next_values.read(h, start, stop), dtype=np.float64)

    def pooled_rows(self, n: int):
        """``(rows, known (n, A) or None)`` of the first ``n`` step-major samples: the next
        observations of steps ``0 .. n/K - 1`` as :class:`CrossedRows` (a view)."""
        K, m = self.psi.shape[1], self.psi.shape[2]
        P = n // K
        rows = CrossedRows(self.psi[1:P + 1].reshape(n, m), None, self.n_actions)
        known = None
        if self.next_values is not None:
            known = np.asarray(self.next_values.lazy(), dtype=float).reshape(-1, self.n_actions)[:n]
        return rows, known

    def take(self, idx, psi: np.ndarray | None = None):
        """The next states of the trajectories ``idx``; ``psi``: their observations' features
        already taken (the taken-action field's subset shares them: one copy, not two)."""
        nv = None if self.next_values is None else self.next_values.subset(idx, "next_values")
        psi = _readonly(self.psi[:, idx]) if psi is None else psi
        return CrossedNext(psi, self.n_actions, nv, self.nonnegative)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a
