"""The constructors of :class:`~r2pvi.OfflineDataset` from sparse rows (``scipy.sparse``):
one CSR matrix per step, a storage kind like memory, files and Dask
(:mod:`~r2pvi.data.storage.sparse_rows`); the dataset is an ``OfflineDataset`` like any
other. Bound to ``OfflineDataset`` as classmethods (see :mod:`~r2pvi.data.build`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from .._validation import as_float_array
from .build import _check_n_actions, check_simplex_features
from .storage import ArrayField, StepSource
from .storage._finite import FIELDS
from .storage.sparse_rows import SparseNext, SparseRowsField, StackedSparse

__all__ = ["from_sparse_rows", "from_sparse_transitions"]


def from_sparse_rows(cls, phi: Sequence, rewards, next_phi: Sequence, n_actions: int,
                     next_values=None):
    """Build a dataset from per-step sparse rows (tile coding, aggregation, one-hot).

    Each step's rows are kept as a CSR matrix: a fit never densifies a row (the Gram matrix is
    factored in its ``K x K`` dual form when ``d > K``, see :class:`~r2pvi.duals.GramFactor`).
    ``step(h)`` returns ``(phi (K, d) CSR, rewards (K,), next_phi StackedSparse (K, A, d),
    next_values)``; there is no dense ``phi``/``next_phi`` view, and ``save`` is not offered
    (both would densify the rows).

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

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> from r2pvi import R2PVI, OfflineDataset
    >>> rng = np.random.default_rng(0)
    >>> K, H, A, d = 40, 3, 2, 1000                 # d >> K, one non-zero per row
    >>> def onehot(idx):
    ...     return sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)),
    ...                          shape=(idx.size, d))
    >>> phi = [onehot(rng.integers(0, 50, K)) for _ in range(H)]
    >>> next_phi = [onehot(rng.integers(0, 50, K * A)) for _ in range(H)]  # row tau * A + a
    >>> ds = OfflineDataset.from_sparse_rows(phi, rng.random((K, H)), next_phi, n_actions=A)
    >>> ds.storage, R2PVI("tv", lam=0.5, beta=0.1).fit(ds).weights_.shape
    ('memory (sparse rows)', (3, 1000))
    """
    A = _check_n_actions(n_actions)
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
    snext = [StackedSparse(_csr(p, f"next_phi[{h}]", (K * A, d), "(K * n_actions, d) = "),
                           (K, A)) for h, p in enumerate(next_phi)]
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
    source = StepSource(SparseRowsField(sphi), ArrayField(np.ascontiguousarray(rewards.T)),
                        SparseNext(snext, None if nv is None else ArrayField(nv)),
                        reward_range=(float(rewards.min()), float(rewards.max())),
                        checked=FIELDS)  # every number checked finite above
    return cls(_source=source)


def from_sparse_transitions(cls, states, actions, rewards, next_states, feature_map,
                            n_actions: int, next_values=None):
    """Build a dataset of sparse rows from observations and a feature map returning sparse
    rows: :func:`from_sparse_rows` of ``feature_map(states (n, ...), actions (n,)) ->
    scipy.sparse (n, d)``, called once per step for the taken actions and once per step and
    action for the next states."""
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
    return from_sparse_rows(cls, phi, rewards, next_phi, A, next_values)


def _csr(x, name: str, shape: tuple[int, int], what: str = ""):
    if not sp.issparse(x):
        raise TypeError(f"{name} must be a scipy.sparse matrix, got {type(x).__name__}")
    m = sp.csr_matrix(x, dtype=float)
    if m.shape != shape:
        raise ValueError(f"{name} must have shape {what}{shape}, got {m.shape}")
    if not np.all(np.isfinite(m.data)):
        raise ValueError(f"{name} contains NaN or infinite entries")
    return m


def sparse_episodes(cls, phi_flat, fmap, nxt, rewards, h_idx, k_idx, absorbing, offset, K, H,
                    A, check_simplex):
    """The dataset of sparse rows of episodes whose feature map returns ``scipy.sparse`` rows
    (:func:`~r2pvi.data.episodes.from_episodes` hands over its flattened transitions): the
    same conventions as the dense path (absorbing values, empty padding rows, padded next
    states repeating a real one), no row densified."""
    N = len(rewards)
    phi_flat = _sparse_rows(phi_flat, N, "feature_map(observations, actions)")
    d = phi_flat.shape[1]
    if check_simplex:
        check_simplex_features(_row_facts(phi_flat), "feature_map(observations, actions)")
    nexts = []
    for a in range(A):
        out = _sparse_rows(fmap(nxt, np.full(N, a)), N, "feature_map(next observations, "
                           "actions)", d)
        if check_simplex:
            check_simplex_features(_row_facts(out[~absorbing]),
                                   "feature_map(next observations, a)")
        nexts.append(out)
    # Row of each (h, k): its flat transition, or -1 (no data at that step).
    where = np.full((H, K), -1, dtype=np.int64)
    where[h_idx, k_idx] = np.arange(N)
    empty = sp.csr_matrix((0, d))
    phi, next_phi = [], []
    next_values = np.full((K, H, A), np.nan)
    next_values[k_idx[absorbing], h_idx[absorbing]] = (H - h_idx[absorbing] - 1)[:, None] * offset
    for h in range(H):
        rows = where[h]
        real = rows >= 0
        phi.append(_scatter_rows(phi_flat, rows, K, d, empty))
        if real.any() and not real.all():  # padding repeats the first real next state
            first = np.flatnonzero(real)[0]
            rows = np.where(real, rows, rows[first])
            next_values[~real, h] = next_values[first, h]
        inter = [_scatter_rows(x, rows, K, d, empty) for x in nexts]
        next_phi.append(sp.vstack(inter, format="csr")[
            (np.arange(A)[None, :] * K + np.arange(K)[:, None]).ravel()])  # row tau * A + a
    rew = np.zeros((K, H))
    rew[k_idx, h_idx] = rewards
    return from_sparse_rows(cls, phi, rew, next_phi, A, next_values)


def _sparse_rows(x, n: int, what: str, d: int | None = None):
    if not sp.issparse(x):
        raise TypeError(f"{what} returned dense rows for some calls and sparse for others")
    m = sp.csr_matrix(x, dtype=float)
    if m.shape[0] != n or (d is not None and m.shape[1] != d):
        want = f"({n}, {'d' if d is None else d})"
        raise ValueError(f"{what} must return {want}, got shape {m.shape}")
    return m


def _scatter_rows(x, rows: np.ndarray, K: int, d: int, empty):
    """``(K, d)`` CSR whose row ``k`` is ``x[rows[k]]`` (an empty row where ``rows[k] < 0``)."""
    real = rows >= 0
    if not real.any():
        return sp.csr_matrix((K, d))
    take = x[rows[real]]
    counts = np.zeros(K, dtype=np.int64)
    counts[real] = np.diff(take.indptr)
    indptr = np.concatenate([[0], np.cumsum(counts)])
    return sp.csr_matrix((take.data, take.indices, indptr), shape=(K, d))


def _row_facts(x) -> np.ndarray:
    """What the simplex check reads of sparse rows, without densifying them: a ``(n, 2)``
    array with each row's smallest entry (0 when a row has zeros) and the rest of its sum."""
    x = sp.csr_matrix(x)
    n = x.shape[0]
    if n == 0:
        return np.zeros((0, 2))
    lo = np.minimum(np.asarray(x.min(axis=1).toarray()).ravel(), 0.0)
    total = np.asarray(x.sum(axis=1)).ravel()
    return np.stack([lo, total - lo], axis=1)


