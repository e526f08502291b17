"""Sparse features (tile coding, aggregation, one-hot): datasets whose rows are ``scipy.sparse``.

Feature maps such as tile coding have tens of thousands of features but only a handful of
non-zeros per row. :class:`SparseOfflineDataset` keeps each step's rows as CSR matrices; the
engine runs the Gram matrix, the regressions, the next-state values and the penalties on them
without densifying a row (the Gram matrix is factored in its K x K dual form when d > K, see
:class:`~r2pvi.duals.GramFactor`), and the duals see the usual expectation operator.

Examples
--------
>>> import numpy as np, scipy.sparse as sp
>>> from r2pvi import R2PVI
>>> from r2pvi.sparse import SparseOfflineDataset
>>> rng = np.random.default_rng(0)
>>> K, H, A, d = 40, 3, 2, 1000                 # d >> K, one non-zero per row
>>> def onehot(idx):
...     return sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), shape=(idx.size, d))
>>> phi = [onehot(rng.integers(0, 50, K)) for _ in range(H)]
>>> next_phi = [onehot(rng.integers(0, 50, K * A)) for _ in range(H)]   # row tau * A + a
>>> ds = SparseOfflineDataset.from_rows(phi, rng.random((K, H)), next_phi, n_actions=A)
>>> est = R2PVI("tv", lam=0.5, beta=0.1).fit(ds)
>>> est.weights_.shape, est.act(next_phi[0][:4].toarray().reshape(2, A, d), h=1).shape
((3, 1000), (2,))
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from ._validation import as_float_array
from .data import OfflineDataset

__all__ = ["StackedSparse", "SparseOfflineDataset", "stack_rows"]


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


def _csr(x, name: str, shape: tuple[int, int], what: str = ""):
    if not sp.issparse(x):
        raise TypeError(f"{name} must be a scipy.sparse matrix, got {type(x).__name__}")
    m = sp.csr_matrix(x, dtype=float)
    if m.shape != shape:
        raise ValueError(f"{name} must have shape {what}{shape}, got {m.shape}")
    if not np.all(np.isfinite(m.data)):
        raise ValueError(f"{name} contains NaN or infinite entries")
    return m


class SparseOfflineDataset(OfflineDataset):
    """An :class:`~r2pvi.OfflineDataset` whose features are sparse rows, one CSR matrix per step.

    Build it with :meth:`from_rows` or :meth:`from_transitions`. ``step(h)`` returns
    ``(phi (K, d) CSR, rewards (K,), next_phi StackedSparse (K, A, d), next_values)``.
    Dense views (``ds.phi``, ``ds.next_phi``) and saving are not offered: they would
    densify the rows.
    """

    def __init__(self, *, _phi, _rewards, _next_phi, _next_values, _d, _A):
        self._sphi = _phi  # H CSR (K, d)
        self._rewards = _rewards  # (H, K)
        self._snext = _next_phi  # H StackedSparse (K, A, d)
        self._next_values = _next_values  # (H, K, A) or None
        self._d, self._A = _d, _A
        self._nonnegative = None
        self._nonnegative_phi = None

    @classmethod
    def from_rows(cls, phi: Sequence, rewards, next_phi: Sequence, n_actions: int,
                  next_values=None) -> SparseOfflineDataset:
        """Build from per-step sparse rows.

        Parameters
        ----------
        phi : sequence of H sparse matrices (K, d)
            Features of the taken actions at each step.
        rewards : array_like (K, H)
        next_phi : sequence of H sparse matrices (K * A, d)
            Row ``tau * A + a`` holds ``phi(s'_tau, a)``; the last step's rows are never used.
        n_actions : int
        next_values : array_like (K, H, A), optional
            Known next-state action values, NaN where learned.
        """
        if isinstance(n_actions, bool) or not isinstance(n_actions, int | np.integer):
            raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
        A = int(n_actions)
        if A < 1:
            raise ValueError(f"n_actions must be >= 1, got {A}")
        for name, rows in (("phi", phi), ("next_phi", next_phi)):
            if not isinstance(rows, Sequence) or isinstance(rows, str | bytes):
                raise TypeError(f"{name} must be a list of H scipy.sparse matrices (one per "
                                f"step), got {type(rows).__name__}")
        rewards = as_float_array(rewards, "rewards", ndim=2)
        K, H = rewards.shape
        if K == 0 or H == 0:
            raise ValueError(f"rewards must have K >= 1 and H >= 1, got {rewards.shape}")
        if len(phi) != H or len(next_phi) != H:
            raise ValueError(
                f"phi and next_phi must hold one sparse matrix per step (H = {H} from rewards), "
                f"got {len(phi)} and {len(next_phi)}"
            )
        if not sp.issparse(phi[0]):
            raise TypeError(f"phi[0] must be a scipy.sparse matrix, got {type(phi[0]).__name__}")
        d = phi[0].shape[1]
        sphi = [_csr(p, f"phi[{h}]", (K, d)) for h, p in enumerate(phi)]
        snext = [StackedSparse(_csr(p, f"next_phi[{h}]", (K * A, d),
                                    "(K * n_actions, d) = "), (K, A))
                 for h, p in enumerate(next_phi)]
        nv = None
        if next_values is not None:
            nv = as_float_array(next_values, "next_values", ndim=3, allow_nan=True)
            if nv.shape != (K, H, A):
                raise ValueError(f"next_values must have shape (K, H, A) = {(K, H, A)}, "
                                 f"got {nv.shape}")
            nv = np.ascontiguousarray(nv.transpose(1, 0, 2))
            nv[H - 1] = np.nan
            if np.isnan(nv).all():
                nv = None
        return cls(_phi=sphi, _rewards=np.ascontiguousarray(rewards.T), _next_phi=snext,
                   _next_values=nv, _d=d, _A=A)

    @classmethod
    def from_transitions(cls, states, actions, rewards, next_states, feature_map,
                         n_actions: int, next_values=None) -> SparseOfflineDataset:
        """Build from observations and a feature map returning sparse rows.

        ``feature_map(states (n, ...), actions (n,)) -> scipy.sparse (n, d)``, called once per
        step for the taken actions and once per step and action for the next states.
        """
        if not callable(feature_map):
            raise TypeError("feature_map must be callable: feature_map(states, actions) -> (n, d)")
        states, next_states = np.asarray(states), np.asarray(next_states)
        actions = np.asarray(actions)
        if actions.ndim != 2 or not np.issubdtype(actions.dtype, np.integer):
            raise TypeError("actions must be an integer array of shape (K, H)")
        K, H = actions.shape
        A = int(n_actions)
        phi, next_phi = [], []
        for h in range(H):
            phi.append(feature_map(states[:, h], actions[:, h]))
            per_action = [sp.csr_matrix(feature_map(next_states[:, h], np.full(K, a)))
                          for a in range(A)]
            # Interleave to row tau * A + a.
            stacked = sp.vstack(per_action, format="csr")
            order = (np.arange(A)[None, :] * K + np.arange(K)[:, None]).ravel()
            next_phi.append(stacked[order])
        return cls.from_rows(phi, rewards, next_phi, A, next_values)

    # ------------------------------------------------------------------ views
    @property
    def _extras(self) -> dict:
        return {}

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.float64)

    @property
    def storage(self) -> str:
        return "memory (sparse rows)"

    @property
    def n_trajectories(self) -> int:
        return self._rewards.shape[1]

    @property
    def horizon(self) -> int:
        return self._rewards.shape[0]

    @property
    def n_features(self) -> int:
        return self._d

    @property
    def n_actions(self) -> int:
        return self._A

    @property
    def nonnegative_next_features(self) -> bool:
        if self._nonnegative is None:
            self._nonnegative = all(bool((m.matrix.data >= 0).all()) for m in self._snext)
        return self._nonnegative

    @property
    def nonnegative_features(self) -> bool:
        if self._nonnegative_phi is None:
            self._nonnegative_phi = all(bool((m.data >= 0).all()) for m in self._sphi)
        return self._nonnegative_phi

    @property
    def phi(self):
        raise TypeError("a SparseOfflineDataset has no dense phi; use step(h)[0] (sparse rows)")

    @property
    def next_phi(self):
        raise TypeError("a SparseOfflineDataset has no dense next_phi; use step(h)[2]")

    @property
    def rewards(self) -> np.ndarray:
        r = self._rewards.T.view()
        r.flags.writeable = False
        return r

    @property
    def next_values(self) -> np.ndarray:
        if self._next_values is None:
            return np.full((self.n_trajectories, self.horizon, self.n_actions), np.nan)
        return self._next_values.transpose(1, 0, 2).copy()

    def step(self, h: int):
        """Step-``h`` data ``(phi CSR (K, d), rewards (K,), next_phi StackedSparse (K, A, d),
        next_values (K, A) or None)``."""
        nv = None if self._next_values is None else self._next_values[h]
        return self._sphi[h], self._rewards[h], self._snext[h], nv

    def _step_product(self, h: int, z: np.ndarray) -> np.ndarray:
        """``phi_h @ z`` for the sparse rows of step ``h`` (float64)."""
        return np.asarray(self._sphi[h] @ z, dtype=np.float64)

    def subset(self, indices) -> SparseOfflineDataset:
        idx = np.asarray(indices)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        if idx.ndim != 1 or idx.size == 0:
            raise ValueError("indices must select at least one trajectory")
        A = self._A
        rows = (idx[:, None] * A + np.arange(A)[None, :]).ravel()
        return SparseOfflineDataset(
            _phi=[m[idx] for m in self._sphi],
            _rewards=np.ascontiguousarray(self._rewards[:, idx]),
            _next_phi=[StackedSparse(m.matrix[rows], (idx.size, A)) for m in self._snext],
            _next_values=None if self._next_values is None
            else np.ascontiguousarray(self._next_values[:, idx]),
            _d=self._d, _A=A,
        )

    def save(self, path, *, dtype=None, overwrite: bool = False, next_form: str = "full"):
        """Not offered (the on-disk format stores dense rows): a ``TypeError``, whatever the
        arguments; nothing is written and nothing at ``path`` is touched."""
        raise TypeError(f"cannot save a SparseOfflineDataset to {path}: saving sparse rows is "
                        "not supported (the on-disk format stores dense rows); keep the feature "
                        "map and the observations, and rebuild it with "
                        "SparseOfflineDataset.from_transitions")

    def __repr__(self) -> str:
        nnz = sum(m.nnz for m in self._sphi)
        return (f"SparseOfflineDataset(K={self.n_trajectories}, H={self.horizon}, "
                f"d={self.n_features}, A={self.n_actions}, nnz(phi)={nnz})")
