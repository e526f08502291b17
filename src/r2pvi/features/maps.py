"""Feature maps from observations onto the probability simplex (the paper's d-rectangular
assumption ``phi_i >= 0, sum_i phi_i = 1``), and their crossing with discrete actions.

- :class:`NormalizedRBF`: Gaussian radial basis functions on a grid (or given centers),
  normalized to sum to 1 (a softmax of ``-||x - c||^2 / (2 sigma^2)``);
- :class:`TileCoding`: tile coding averaged over tilings (each row has ``n_tilings`` entries
  equal to ``1 / n_tilings``), dense or ``scipy.sparse`` CSR;
- :class:`StateAggregation`: hard aggregation on a grid (one-hot cells);
- :class:`ActionCrossing` / :func:`cross_actions`: ``phi(s, a) = e_a (x) psi(s)``, block-wise,
  the callable ``feature_map(observations, actions) -> (n, A m)`` that
  :meth:`r2pvi.OfflineDataset.from_episodes` takes.

All maps follow scikit-learn's transformer conventions (``fit`` learns the observation ranges,
``transform`` maps), are vectorized and deterministic (random tile offsets take a ``seed``).
"""

from __future__ import annotations

import numpy as np

from ._base import (
    ObservationTransformer,
    check_positive_int_or_seq,
    grid_indices,
    register_saveable,
)
from ._io import SaveableMap

__all__ = [
    "NormalizedRBF",
    "TileCoding",
    "StateAggregation",
    "ActionCrossing",
    "cross_actions",
    "as_feature_map",
]


class NormalizedRBF(SaveableMap, ObservationTransformer):
    """Normalized Gaussian RBF features: ``psi_j(x) = softmax_j(-||z - c_j||^2 / (2 s^2))``.

    Observations are first scaled to the unit box ``z = (x - low) / (high - low)`` with the
    ranges learned by :meth:`fit` (or given), so one bandwidth fits every dimension.

    Parameters
    ----------
    n_centers : int or sequence of int, default 5
        Grid centers per observation dimension (``prod(n_centers)`` features); ignored when
        ``centers`` is given.
    centers : array_like (m, D), optional
        Centers in observation units instead of a grid.
    bandwidth : float, optional
        ``s`` in unit-box coordinates; None takes the grid spacing ``1 / (n - 1)`` per
        dimension (the median nearest-neighbour distance of given centers).
    ranges : array_like (D, 2), optional
        ``(low, high)`` per dimension; None learns them from the data in :meth:`fit`.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.features import NormalizedRBF
    >>> X = np.random.default_rng(0).normal(size=(100, 2))
    >>> rbf = NormalizedRBF(n_centers=3).fit(X)
    >>> psi = rbf.transform(X[:4])
    >>> psi.shape, bool(np.allclose(psi.sum(axis=1), 1.0)), bool((psi >= 0).all())
    ((4, 9), True, True)
    """

    def __init__(self, n_centers=5, *, centers=None, bandwidth=None, ranges=None):
        self.n_centers = n_centers
        self.centers = centers
        self.bandwidth = bandwidth
        self.ranges = ranges

    def _fit_more(self, X):
        D = X.shape[1]
        if self.centers is not None:
            c = np.asarray(self.centers, dtype=float)
            if c.ndim == 1 and D == 1:
                c = c[:, None]
            if c.ndim != 2 or c.shape[1] != D or c.shape[0] < 1 or not np.isfinite(c).all():
                raise ValueError(
                    f"centers must be a finite (m, D={D}) array of observation points, "
                    f"got shape {c.shape}"
                )
            self.centers_ = self._unit(c)
            if self.bandwidth is None:
                if len(c) == 1:
                    sigma = np.ones(D)
                else:
                    sq = _sq_dists(self.centers_, self.centers_)
                    np.fill_diagonal(sq, np.inf)
                    sigma = np.full(D, max(float(np.median(np.sqrt(sq.min(axis=1)))), 1e-12))
            else:
                sigma = np.full(D, _positive(self.bandwidth, "bandwidth"))
        else:
            n = check_positive_int_or_seq(self.n_centers, "n_centers", D)
            axes = [np.linspace(0.0, 1.0, k) if k > 1 else np.array([0.5]) for k in n]
            mesh = np.meshgrid(*axes, indexing="ij")
            self.centers_ = np.stack([m.reshape(-1) for m in mesh], axis=1)
            if self.bandwidth is None:
                sigma = np.where(n > 1, 1.0 / np.maximum(n - 1, 1), 1.0)
            else:
                sigma = np.full(D, _positive(self.bandwidth, "bandwidth"))
        self.sigma_ = sigma.astype(float)
        self.n_features_out_ = self.centers_.shape[0]

    def transform(self, X):
        """Normalized RBF features ``(n, m)`` (rows on the simplex)."""
        z = self._scaled(X) / self.sigma_
        logits = -0.5 * _sq_dists(z, self.centers_ / self.sigma_)
        logits -= logits.max(axis=1, keepdims=True)
        np.exp(logits, out=logits)
        logits /= logits.sum(axis=1, keepdims=True)
        return logits


class TileCoding(SaveableMap, ObservationTransformer):
    """Tile coding averaged over tilings: ``psi(x) = (1/T) sum_t onehot(tile_t(x))``.

    Each of the ``n_tilings`` grids has ``n_tiles + 1`` tiles per dimension and is shifted by
    a fraction of a tile, so every tiling covers the (learned) range. A row has exactly
    ``n_tilings`` entries ``1 / n_tilings``: it lies on the simplex.

    Parameters
    ----------
    n_tilings : int, default 8
    n_tiles : int or sequence of int, default 4
        Tiles across the range per dimension (each tiling has one more to cover its shift).
    offsets : {"uniform", "random"}, default "uniform"
        ``"uniform"``: tiling ``t`` is shifted by ``t (2j + 1) / T`` tiles (mod 1) in dimension
        ``j`` (Sutton & Barto's asymmetric displacement); ``"random"``: uniform shifts drawn
        from ``seed``.
    seed : int, SeedSequence or Generator, optional
        Random offsets only.
    ranges : array_like (D, 2), optional
        ``(low, high)`` per dimension; None learns them from the data.
    sparse : bool, default False
        Return ``scipy.sparse.csr_matrix`` rows instead of a dense array.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.features import TileCoding
    >>> X = np.random.default_rng(0).uniform(size=(50, 2))
    >>> tc = TileCoding(n_tilings=4, n_tiles=3).fit(X)
    >>> psi = tc.transform(X[:2])
    >>> psi.shape, np.unique(psi[0]).tolist()
    ((2, 64), [0.0, 0.25])
    >>> TileCoding(n_tilings=4, n_tiles=3, sparse=True).fit(X).transform(X[:2]).nnz
    8
    """

    def __init__(self, n_tilings=8, n_tiles=4, *, offsets="uniform", seed=None, ranges=None,
                 sparse=False):
        self.n_tilings = n_tilings
        self.n_tiles = n_tiles
        self.offsets = offsets
        self.seed = seed
        self.ranges = ranges
        self.sparse = sparse

    def _fit_more(self, X):
        D = X.shape[1]
        T = int(check_positive_int_or_seq(self.n_tilings, "n_tilings", 1)[0])
        n = check_positive_int_or_seq(self.n_tiles, "n_tiles", D)
        if self.offsets == "uniform":
            disp = 2 * np.arange(D) + 1
            off = (np.arange(T)[:, None] * disp[None, :] / T) % 1.0
        elif self.offsets == "random":
            off = np.random.default_rng(self.seed).uniform(size=(T, D))
        else:
            raise ValueError(f"offsets must be 'uniform' or 'random', got {self.offsets!r}")
        if not isinstance(self.sparse, bool | np.bool_):
            raise TypeError(f"sparse must be True or False, got {self.sparse!r}")
        self.tile_offsets_ = off
        self.n_tilings_ = T
        self.cells_ = n + 1
        self.tiling_size_ = int(np.prod(self.cells_))
        self.n_features_out_ = T * self.tiling_size_

    def active_tiles(self, X) -> np.ndarray:
        """Indices ``(n, n_tilings)`` of the active feature in every tiling."""
        u = self._scaled(X)
        cols = np.empty((u.shape[0], self.n_tilings_), dtype=np.int64)
        for t in range(self.n_tilings_):
            cols[:, t] = t * self.tiling_size_ + grid_indices(u, self.cells_, self.tile_offsets_[t])
        return cols

    def transform(self, X):
        """Tile-coded features ``(n, n_tilings (n_tiles + 1)^D)`` (dense or CSR)."""
        cols = self.active_tiles(X)
        return _rows_from_columns(cols, self.n_features_out_, bool(self.sparse))


class StateAggregation(SaveableMap, ObservationTransformer):
    """Hard state aggregation: the one-hot cell of a grid of ``n_bins`` per dimension.

    Observations outside the learned range fall in the edge cells.

    Parameters
    ----------
    n_bins : int or sequence of int, default 10
    ranges : array_like (D, 2), optional
        ``(low, high)`` per dimension; None learns them from the data.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.features import StateAggregation
    >>> agg = StateAggregation(n_bins=2).fit([[0.0, 0.0], [1.0, 1.0]])
    >>> agg.transform([[0.1, 0.9], [0.9, 0.1]])
    array([[0., 1., 0., 0.],
           [0., 0., 1., 0.]])
    """

    def __init__(self, n_bins=10, *, ranges=None):
        self.n_bins = n_bins
        self.ranges = ranges

    def _fit_more(self, X):
        self.cells_ = check_positive_int_or_seq(self.n_bins, "n_bins", X.shape[1])
        self.n_features_out_ = int(np.prod(self.cells_))

    def transform(self, X):
        """One-hot cells ``(n, prod(n_bins))``."""
        idx = grid_indices(self._scaled(X), self.cells_)
        return _rows_from_columns(idx[:, None], self.n_features_out_, False)


@register_saveable
class ActionCrossing(SaveableMap):
    """``phi(s, a) = e_a (x) psi(s)``: observation features placed in the block of the action.

    With ``psi`` on the simplex, so is ``phi`` (dimension ``n_actions * m``). The result is
    the callable ``feature_map(observations, actions) -> (n, d)`` of
    :meth:`r2pvi.OfflineDataset.from_episodes` and :meth:`~r2pvi.LinearEstimator.as_policy`.

    Parameters
    ----------
    state_map : fitted transformer
        Anything with ``transform(observations) -> (n, m)``: an r2pvi map or a fitted
        scikit-learn transformer (dense or sparse output).
    n_actions : int

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.features import StateAggregation, cross_actions
    >>> fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), n_actions=2)
    >>> fmap(np.array([[0.2], [0.8]]), np.array([1, 0]))
    array([[0., 0., 1., 0.],
           [0., 1., 0., 0.]])
    """

    def __init__(self, state_map, n_actions: int):
        if not callable(getattr(state_map, "transform", None)):
            raise TypeError(
                "state_map must have transform(observations) -> (n, m) (an r2pvi feature map "
                f"or a fitted scikit-learn transformer), got {type(state_map).__name__}"
            )
        if isinstance(n_actions, bool) or not isinstance(n_actions, int | np.integer):
            raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
        if n_actions < 1:
            raise ValueError(f"n_actions must be >= 1, got {n_actions}")
        self.state_map = state_map
        self.n_actions = int(n_actions)

    def fit(self, X, y=None):
        """Fit the observation map on ``X`` and return ``self``."""
        self.state_map.fit(X)
        return self

    def state_features(self, observations):
        """``psi(observations)``: ``(n, m)`` dense or sparse."""
        return self.state_map.transform(observations)

    def __call__(self, observations, actions):
        """``phi(observations, actions)``: ``(n, n_actions * m)``."""
        return self.cross(self.state_features(observations), actions)

    def all_actions(self, observations):
        """Features of every action at each observation, ``(n, A, d)`` (dense)."""
        psi = _dense(self.state_features(observations))
        n, m = psi.shape
        A = self.n_actions
        out = np.zeros((n, A, A * m))
        for a in range(A):
            out[:, a, a * m:(a + 1) * m] = psi
        return out

    def cross(self, psi, actions):
        """Place the rows of ``psi (n, m)`` in the blocks of ``actions (n,)``."""
        a = _check_actions(actions, self.n_actions)
        import scipy.sparse as sp

        if sp.issparse(psi):
            csr = sp.csr_matrix(psi)
            if csr.shape[0] != a.shape[0]:
                raise ValueError("observations and actions must have the same length")
            m = csr.shape[1]
            counts = np.diff(csr.indptr)
            cols = csr.indices + np.repeat(a * m, counts)
            return sp.csr_matrix((csr.data, cols, csr.indptr), shape=(csr.shape[0],
                                                                      self.n_actions * m))
        psi = np.asarray(psi, dtype=float)
        if psi.ndim != 2 or psi.shape[0] != a.shape[0]:
            raise ValueError(
                f"the state map returned shape {psi.shape}; expected ({a.shape[0]}, m)"
            )
        n, m = psi.shape
        out = np.zeros((n, self.n_actions * m))
        out[np.arange(n)[:, None], a[:, None] * m + np.arange(m)] = psi
        return out

    @property
    def n_features_out_(self) -> int:
        """``d = n_actions * m``."""
        return self.n_actions * int(self.state_map.n_features_out_)

    def __repr__(self) -> str:
        return f"ActionCrossing({self.state_map!r}, n_actions={self.n_actions})"


def cross_actions(state_map, n_actions: int) -> ActionCrossing:
    """``feature_map(observations, actions)`` from an observation map (:class:`ActionCrossing`)."""
    return ActionCrossing(state_map, n_actions)


def as_feature_map(feature_map, n_actions: int):
    """Any accepted feature map as a callable ``feature_map(observations, actions) -> (n, d)``.

    A callable is used as is; an object with ``transform`` (a fitted observation map or
    scikit-learn transformer) is crossed with the actions (:class:`ActionCrossing`).
    """
    if callable(feature_map):
        return feature_map
    if callable(getattr(feature_map, "transform", None)):
        return ActionCrossing(feature_map, n_actions)
    raise TypeError(
        "feature_map must be a callable feature_map(observations, actions) -> (n, d) or a "
        "fitted transformer with transform(observations) (crossed with the actions), got "
        f"{type(feature_map).__name__}"
    )


# ---------------------------------------------------------------------- helpers
def _sq_dists(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``||a_i - b_j||^2`` (n, m) by one GEMM, clipped at 0 against round-off."""
    out = (a * a).sum(axis=1)[:, None] - 2.0 * (a @ b.T) + (b * b).sum(axis=1)[None, :]
    np.maximum(out, 0.0, out=out)
    return out


def _positive(value, name: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def _rows_from_columns(cols: np.ndarray, d: int, sparse: bool):
    """Rows with ``1 / k`` at each of the ``k`` columns ``cols (n, k)``: dense or CSR."""
    n, k = cols.shape
    if sparse:
        import scipy.sparse as sp

        data = np.full(n * k, 1.0 / k)
        indptr = np.arange(0, n * k + 1, k)
        return sp.csr_matrix((data, cols.reshape(-1), indptr), shape=(n, d))
    out = np.zeros((n, d))
    out[np.arange(n)[:, None], cols] = 1.0 / k  # the k columns of a row are distinct
    return out


def _dense(x) -> np.ndarray:
    if hasattr(x, "toarray"):
        return x.toarray()
    return np.asarray(x, dtype=float)


def _check_actions(actions, n_actions: int) -> np.ndarray:
    a = np.asarray(actions)
    if a.dtype == bool or a.dtype.kind not in "iuf":
        raise TypeError(f"actions must be integer indices, got dtype {a.dtype}")
    a = a.reshape(-1) if a.ndim > 1 and a.shape[1:] == (1,) * (a.ndim - 1) else a
    if a.ndim != 1:
        raise ValueError(f"actions must have shape (n,), got {np.shape(actions)}")
    if a.dtype.kind == "f":
        if not np.all(a == np.round(a)):
            raise TypeError("actions must be integer indices, got non-integer values")
    a = a.astype(np.int64)
    if a.size and ((a < 0) | (a >= n_actions)).any():
        hint = (f": this feature map was built for n_actions={n_actions} (cross_actions(..., "
                f"n_actions={n_actions})); pass the same n_actions to the dataset or policy, "
                "or rebuild the map" if a.max() >= n_actions else "")
        raise ValueError(f"actions must lie in [0, {n_actions}), got {a.min()}..{a.max()}"
                         + hint)
    return a
