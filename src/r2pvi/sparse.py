"""Sparse features (tile coding, aggregation, one-hot): datasets whose rows are ``scipy.sparse``.

Sparse rows are a storage kind of the one :class:`~r2pvi.OfflineDataset`
(:mod:`r2pvi.data.storage.sparse_rows`): each step's rows are kept as a CSR matrix, and the
engine runs the Gram matrix, the regressions, the next-state values and the penalties on them
without densifying a row (the Gram matrix is factored in its K x K dual form when d > K, see
:class:`~r2pvi.duals.GramFactor`); the duals see the usual expectation operator.
:class:`SparseOfflineDataset` names the constructors (it is not a class of datasets: it
returns an ``OfflineDataset``).

Examples
--------
>>> import numpy as np, scipy.sparse as sp
>>> from r2pvi import R2PVI, OfflineDataset
>>> from r2pvi.sparse import SparseOfflineDataset
>>> rng = np.random.default_rng(0)
>>> K, H, A, d = 40, 3, 2, 1000                 # d >> K, one non-zero per row
>>> def onehot(idx):
...     return sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), shape=(idx.size, d))
>>> phi = [onehot(rng.integers(0, 50, K)) for _ in range(H)]
>>> next_phi = [onehot(rng.integers(0, 50, K * A)) for _ in range(H)]   # row tau * A + a
>>> ds = SparseOfflineDataset.from_rows(phi, rng.random((K, H)), next_phi, n_actions=A)
>>> type(ds) is OfflineDataset, ds.storage
(True, 'memory (sparse rows)')
>>> est = R2PVI("tv", lam=0.5, beta=0.1).fit(ds)
>>> est.weights_.shape, est.act(next_phi[0][:4].toarray().reshape(2, A, d), h=1).shape
((3, 1000), (2,))
"""

from __future__ import annotations

from .data.build_sparse import from_sparse_transitions
from .data.dataset import OfflineDataset
from .data.storage.sparse_rows import StackedSparse, stack_rows

__all__ = ["StackedSparse", "SparseOfflineDataset", "stack_rows"]


class SparseOfflineDataset:
    """The constructors of an :class:`~r2pvi.OfflineDataset` of sparse rows (a namespace:
    there is one dataset class, and sparse rows are one of its storage kinds).

    ``step(h)`` of the dataset returns ``(phi (K, d) CSR, rewards (K,), next_phi
    StackedSparse (K, A, d), next_values)``. Dense views (``ds.phi``, ``ds.next_phi``) and
    saving are not offered: they would densify the rows.
    """

    def __init__(self):
        raise TypeError("SparseOfflineDataset is not a class of datasets: build an "
                        "OfflineDataset of sparse rows with SparseOfflineDataset.from_rows(...) "
                        "or OfflineDataset.from_sparse_rows(...)")

    @staticmethod
    def from_rows(phi, rewards, next_phi, n_actions: int, next_values=None) -> OfflineDataset:
        """:meth:`OfflineDataset.from_sparse_rows <r2pvi.OfflineDataset.from_sparse_rows>`:
        per-step sparse rows ``phi`` (H matrices ``(K, d)``), ``rewards (K, H)``, ``next_phi``
        (H matrices ``(K * A, d)``, row ``tau * A + a``), ``n_actions``, ``next_values``."""
        return OfflineDataset.from_sparse_rows(phi, rewards, next_phi, n_actions, next_values)

    @staticmethod
    def from_transitions(states, actions, rewards, next_states, feature_map, n_actions: int,
                         next_values=None) -> OfflineDataset:
        """An :class:`~r2pvi.OfflineDataset` of sparse rows from observations and a feature
        map returning sparse rows, ``feature_map(states (n, ...), actions (n,)) ->
        scipy.sparse (n, d)``, called once per step for the taken actions and once per step
        and action for the next states."""
        return from_sparse_transitions(OfflineDataset, states, actions, rewards, next_states,
                                       feature_map, n_actions, next_values)
