"""The one dataset: K trajectories of length H with linear features.

The data model is feature-first: what every algorithm needs from a transition
``(s_h, a_h, r_h, s_{h+1})`` is the feature vector of the taken action ``phi(s_h, a_h)``,
the reward, and the features of *every* action at the next state ``phi(s_{h+1}, a')``,
from which the next step's value ``max_a' Q_{h+1}(s_{h+1}, a')`` is computed.
Next-state actions whose value is known (an absorbing fail state, a stopping action
with a known payoff) carry that value in ``next_values``; NaN means "learn it".

The numbers live in a step-major :class:`~r2pvi.data.storage.StepSource` (in memory, in a
dataset directory on disk, in Dask arrays, as sparse rows, or as observations and a feature
map); see :mod:`r2pvi.data.storage`. The constructors are in :mod:`~r2pvi.data.build`,
:mod:`~r2pvi.data.build_observations` and :mod:`~r2pvi.data.episodes`; saving and opening
in :mod:`~r2pvi.data.files`.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_index_array
from . import build, build_observations, build_sparse, episodes, files
from .build import check_simplex_features
from .storage import SimplexFeatureWarning
from .storage.fields import readonly

__all__ = ["OfflineDataset", "SimplexFeatureWarning", "check_simplex_features",
           "dataset_from_episodes"]


class OfflineDataset:
    """K trajectories of length H, as features of taken and next-state actions.

    Build it with :meth:`from_features`, :meth:`from_transitions`,
    :meth:`from_next_state_table`, :meth:`from_observations`, :meth:`from_episodes`,
    :meth:`from_dask`, :meth:`from_sparse_rows`, or open a dataset directory with
    :meth:`open`; do not call the constructor directly. The numbers are stored step-major
    (the engine reads one step at a time, a chunk of trajectories at a time) and exposed
    trajectory-major, as the constructors take them.

    Attributes
    ----------
    phi : ndarray (K, H, d)
        Features ``phi(s_h, a_h)`` of the taken actions.
    rewards : ndarray (K, H)
        Observed rewards ``r_h``.
    next_phi : ndarray (K, H, A, d)
        Features ``phi(s_{h+1}, a)`` of every action at the next state. Row ``h = H-1``
        is never used (the value after the last step is 0).
    next_values : ndarray (K, H, A)
        Known values of next-state actions, NaN where the value must be learned.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> rng = np.random.default_rng(0)
    >>> phi = rng.dirichlet(np.ones(3), size=(5, 2))          # K=5, H=2, d=3
    >>> next_phi = rng.dirichlet(np.ones(3), size=(5, 2, 4))  # A=4 next actions
    >>> ds = OfflineDataset.from_features(phi, rng.random((5, 2)), next_phi)
    >>> ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions
    (5, 2, 3, 4)
    """


    def __init__(self, *, _source):
        # Private: the public constructors validate and hand over a step source.
        self._source = _source
        self._nonnegative: bool | None = _source.next.nonnegative
        self._nonnegative_phi: bool | None = _source.nonnegative_phi

    # ------------------------------------------------------------------ constructors
    # (each validates its arguments and hands the class a step source: data/build*.py)
    from_features = classmethod(build.from_features)
    from_next_state_table = classmethod(build.from_next_state_table)
    from_dask = classmethod(build.from_dask)
    from_transitions = classmethod(build_observations.from_transitions)
    from_observations = classmethod(build_observations.from_observations)
    from_episodes = classmethod(episodes.from_episodes)
    from_sparse_rows = classmethod(build_sparse.from_sparse_rows)

    # ------------------------------------------------------------------ views
    @property
    def n_trajectories(self) -> int:
        """K, the number of trajectories."""
        return self._source.n_trajectories

    @property
    def horizon(self) -> int:
        """H, the number of steps."""
        return self._source.horizon

    @property
    def n_features(self) -> int:
        """d, the feature dimension."""
        return self._source.n_features

    @property
    def n_actions(self) -> int:
        """A, the number of actions at the next states."""
        return self._source.n_actions

    @property
    def dtype(self) -> np.dtype:
        """Storage type of the features (float32 or float64); fits accumulate in float64."""
        return self._source.phi.dtype

    @property
    def storage(self) -> str:
        """Where the data lives: ``"memory"``, ``"disk"``, ``"dask"`` or ``"memory (sparse
        rows)"``."""
        return self._source.phi.storage

    @property
    def phi(self) -> np.ndarray:
        """Features of the taken actions, (K, H, d) (a read-only view; a memory map on disk)."""
        return readonly(self._source.phi.lazy().swapaxes(0, 1))

    @property
    def rewards(self) -> np.ndarray:
        """Rewards, (K, H) (a read-only view)."""
        return readonly(self._source.rewards.lazy().swapaxes(0, 1))

    @property
    def next_phi(self) -> np.ndarray:
        """Features of every next-state action, (K, H, A, d) (a read-only view when stored;
        computed, and so materialized, when they come from a table or a feature map)."""
        return readonly(self._source.next.all_features(self.horizon))

    @property
    def next_values(self) -> np.ndarray:
        """Known next-state action values, (K, H, A), NaN where learned."""
        K, H, A = self.n_trajectories, self.horizon, self.n_actions
        nxt = self._source.next
        if not nxt.has_known_values:
            return np.full((K, H, A), np.nan)
        out = np.full((K, H, A), np.nan)
        for h in range(H - 1):  # the last step's row is never used
            out[:, h] = nxt.known(h)
        return out

    @property
    def nonnegative_next_features(self) -> bool:
        """Whether every next-state feature is >= 0 (computed once, then cached)."""
        if self._nonnegative is None:
            self._nonnegative = self._source.next.find_nonnegative(
                self.horizon, self.n_trajectories, self._source.chunk)
        return self._nonnegative

    @property
    def nonnegative_features(self) -> bool:
        """Whether every taken-action feature is >= 0 (computed once, then cached)."""
        if self._nonnegative_phi is None:
            self._nonnegative_phi = self._source.phi.nonnegative(self._source.chunk)
        return self._nonnegative_phi

    @property
    def reward_range(self) -> tuple[float, float]:
        """The rewards' ``(min, max)`` as Python floats: taken while the data was validated
        (or recorded in a dataset directory's manifest), else read once from the rewards
        alone, never the features; then kept. ``fit`` checks it against the estimator's
        ``r_max``.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> ds = OfflineDataset.from_features(np.full((2, 3, 2), 0.5), [[0, 1, 2], [3, 4, 5]],
        ...                                   np.full((2, 3, 1, 2), 0.5))
        >>> ds.reward_range
        (0.0, 5.0)
        """
        return self._source.reward_bounds()

    @property
    def reward_noise(self) -> float:
        """Standard deviation of zero-mean noise on the observed rewards (0: exact rewards).

        Set by ``reward_noise=`` of :meth:`from_features` and :meth:`from_next_state_table`
        (``FiniteLinearMDP.collect`` passes its own); kept by :meth:`subset`, :meth:`save`
        and :meth:`open`. ``fit`` checks the rewards against ``[0, r_max]`` up to
        ``8 * reward_noise``: noisy samples of in-range mean rewards leave the range, a
        wrong reward scale does not hide in the noise."""
        return self._source.reward_noise

    @property
    def stationary(self) -> bool:
        """Whether the steps are draws of one stationary environment (the same dynamics and
        rewards at every step), so that the estimators' default ``time_homogeneous="auto"``
        pools them (one regression over every transition). True for datasets built by
        :meth:`from_episodes` (Gymnasium rollouts, Minari datasets), kept by :meth:`subset`,
        :meth:`save` and :meth:`open`; False for the other constructors (a finite MDP's
        step-dependent factors, the paper's experiments: fitted per step). An estimator's
        ``time_homogeneous=True`` or ``False`` overrides it.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> ep = {"observations": [[0.0], [1.0]], "actions": [0], "rewards": [1.0],
        ...       "terminations": [True], "truncations": [False]}
        >>> OfflineDataset.from_episodes([ep], lambda o, a: np.ones((len(a), 1)), 1).stationary
        True
        """
        return self._source.stationary

    @property
    def has_known_values(self) -> bool:
        """Whether any next-state action value is given."""
        return self._source.next.has_known_values

    @property
    def states(self):
        """Observed states (K, H, ...) when built by :meth:`from_transitions`, else None."""
        return self._source.extras.get("states")

    @property
    def actions(self):
        """Taken action indices (K, H) when built by :meth:`from_transitions`, else None."""
        return self._source.extras.get("actions")

    @property
    def next_states(self):
        """Observed next states (K, H, ...) when built by :meth:`from_transitions`, else None."""
        return self._source.extras.get("next_states")

    @property
    def _extras(self) -> dict:
        return self._source.extras

    def initial_features(self) -> np.ndarray | None:
        """Features ``phi(s_0, a)`` of every action at each trajectory's initial state,
        ``(K, A, d)`` float64, when the dataset holds them; else None.

        Held by datasets of episodes stored as state features (:meth:`from_episodes` with a
        feature map crossed with the actions: ``psi(s_0)`` crossed with every action) and by
        observations with a feature map (:meth:`from_observations`: the map at the first
        observations). The other layouts store only the taken action's features, not every
        action's at ``s_0``. It is what the estimators' ``score(kind="fqe")`` averages over by
        default.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> from r2pvi.features import StateAggregation, cross_actions
        >>> ep = {"observations": [[0.2], [0.9]], "actions": [1], "rewards": [1.0],
        ...       "terminations": [True], "truncations": [False]}
        >>> fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), 2)
        >>> OfflineDataset.from_episodes([ep], fmap, 2).initial_features().tolist()  # (K, A, d)
        [[[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]]
        >>> print(OfflineDataset.from_features(np.ones((1, 1, 2)) / 2, [[1.0]],
        ...                                    np.ones((1, 1, 2, 2)) / 2).initial_features())
        None
        """
        phi = self._source.phi
        if hasattr(phi, "crossed_step"):  # state features psi once per observation
            from .storage.crossed import cross_rows

            return cross_rows(np.asarray(phi.psi[0], dtype=np.float64), None, phi.n_actions)
        if hasattr(phi, "feature_map") and hasattr(phi, "observations"):
            obs = phi.observations.read(0)
            n = obs.shape[0]
            return np.stack([np.asarray(phi.feature_map(obs, np.full(n, a)), dtype=np.float64)
                             for a in range(self.n_actions)], axis=1)
        return None

    def step(self, h: int):
        """Step-``h`` arrays ``(phi (K,d), rewards (K,), next_phi (K,A,d), next_values)``.

        ``next_values`` is ``(K, A)`` with NaN where learned, or None if none is known.
        ``h`` is 0-based. The whole step is read (the engine reads it in chunks instead).
        Sparse rows (:meth:`from_sparse_rows`) come as they are stored: ``phi`` a CSR matrix,
        ``next_phi`` a :class:`~r2pvi.data.storage.sparse_rows.StackedSparse`.
        """
        return self._source.step(h)

    def step_phi(self, h: int) -> np.ndarray:
        """Step ``h``'s taken-action features ``(K, d)`` in float64 (a view when stored so;
        a CSR matrix for sparse rows)."""
        return self._source.phi_step(h)

    def step_times(self, h: int, z) -> np.ndarray:
        """``phi_h @ z``: step ``h``'s taken-action features times ``z`` (``(d,)`` or
        ``(d, m)``), in float64, formed chunk by chunk where the data is (on the workers for
        Dask arrays), so only the ``K`` (or ``K x m``) products are held.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> rng = np.random.default_rng(0)
        >>> ds = OfflineDataset.from_features(rng.dirichlet(np.ones(3), (5, 2)),
        ...                                   np.zeros((5, 2)),
        ...                                   rng.dirichlet(np.ones(3), (5, 2, 2)))
        >>> z = np.array([1.0, -1.0, 2.0])
        >>> bool(np.allclose(ds.step_times(1, z), ds.phi[:, 1] @ z))
        True
        """
        z = np.asarray(z, dtype=np.float64)
        if z.ndim not in (1, 2) or z.shape[0] != self.n_features:
            raise ValueError(f"z must have shape (d,) or (d, m) with d = {self.n_features}, "
                             f"got {z.shape}")
        return self._step_product(h, z)

    def _step_product(self, h: int, z: np.ndarray) -> np.ndarray:
        """``phi_h @ z`` for a validated float64 ``z`` (the storage decides where)."""
        return self._source.phi_times(h, z)

    def subset(self, indices) -> OfflineDataset:
        """The dataset restricted to the trajectories ``indices`` (for bootstraps, splits);
        in memory, whatever the storage.

        ``indices`` is an array of integer indices in ``[0, K)`` (repeats allowed, as in a
        bootstrap) or a boolean mask of length K. ``dataset[indices]`` is the same, with
        slices and negative indices too."""
        idx = np.asarray(indices)
        if idx.dtype == bool:
            if idx.shape != (self.n_trajectories,):
                raise ValueError(
                    f"a boolean mask must have one entry per trajectory (K = "
                    f"{self.n_trajectories}), got shape {idx.shape}"
                )
            idx = np.flatnonzero(idx)
        if idx.ndim != 1 or idx.size == 0:
            raise ValueError("indices must select at least one trajectory")
        idx = as_index_array(idx, "indices", self.n_trajectories, ndim=1)
        return OfflineDataset(_source=self._source.take(idx))

    # ------------------------------------------------------------------ trajectories
    def __len__(self) -> int:
        """K, the number of trajectories: the dataset is a sequence of trajectories (what
        scikit-learn's splitters count)."""
        return self.n_trajectories

    @property
    def shape(self) -> tuple[int]:
        """``(K,)``: the dataset seen as a sequence of K trajectories. scikit-learn reads it
        to count samples and to index by rows (``dataset[indices, ...]``), so ``KFold``,
        ``cross_val_score`` and ``GridSearchCV`` split by trajectory without glue."""
        return (self.n_trajectories,)

    def __getitem__(self, key) -> OfflineDataset:
        """The trajectories selected by ``key``, as a dataset (see :meth:`subset`).

        ``key`` is an array of integer indices (negative ones count from the end), a slice,
        or a boolean mask with one entry per trajectory; ``key, ...`` (what scikit-learn
        passes) is the same. A single integer is refused: ``dataset[[k]]`` is trajectory
        ``k`` as a dataset.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> rng = np.random.default_rng(0)
        >>> ds = OfflineDataset.from_features(rng.dirichlet(np.ones(3), (6, 2)),
        ...                                   rng.random((6, 2)),
        ...                                   rng.dirichlet(np.ones(3), (6, 2, 2)))
        >>> len(ds), len(ds[1:4]), len(ds[np.array([0, -1])]), len(ds[ds.rewards[:, 0] > 0.5])
        (6, 3, 2, 3)
        """
        if isinstance(key, tuple):
            if len(key) == 2 and key[1] is Ellipsis:
                key = key[0]
            else:
                raise TypeError(
                    "an OfflineDataset is indexed by trajectories only: dataset[indices], not "
                    f"a tuple of {len(key)} keys; use dataset.step(h) for one step")
        K = self.n_trajectories
        if isinstance(key, slice):
            idx = np.arange(K)[key]
            if idx.size == 0:
                raise ValueError(f"the slice {key} selects no trajectory (K = {K})")
            return self.subset(idx)
        if isinstance(key, int | np.integer) and not isinstance(key, bool | np.bool_):
            raise TypeError(
                f"an OfflineDataset is indexed by arrays of trajectories; for trajectory {key} "
                f"as a dataset, pass dataset[[{key}]]")
        idx = np.asarray(key)
        if idx.dtype != bool and idx.dtype.kind in "iu" and idx.ndim == 1 and idx.size:
            if idx.min() < -K or idx.max() >= K:
                raise ValueError(
                    f"trajectory indices must lie in [-{K}, {K}) (K = {K}), got values from "
                    f"{int(idx.min())} to {int(idx.max())}")
            idx = np.where(idx < 0, idx + K, idx)
        return self.subset(idx)

    def __iter__(self):
        raise TypeError(
            "an OfflineDataset is not iterated trajectory by trajectory; select trajectories "
            "with dataset[indices] or read a step with dataset.step(h)")

    def __repr__(self) -> str:
        return (
            f"OfflineDataset(K={self.n_trajectories}, H={self.horizon}, d={self.n_features}, "
            f"A={self.n_actions}, known_values={self.has_known_values}"
            f"{self._source.phi.describe()})"
        )

    # ------------------------------------------------------------------ I/O (data/files.py)
    save = files.save
    open = classmethod(files.open_dataset)
    load = classmethod(files.load)


def dataset_from_episodes(episodes, feature_map, n_actions: int, horizon: int | None = None, *,
                          reward_offset=None, check_simplex: bool = True,
                          dtype=None) -> OfflineDataset:
    """Build an :class:`~r2pvi.OfflineDataset` from episodes of any length.

    The same as :meth:`r2pvi.OfflineDataset.from_episodes` (the public entry point); see
    :mod:`r2pvi.episodes` for the conventions (termination, truncation, padding, reward
    offsets).
    """
    return OfflineDataset.from_episodes(episodes, feature_map, n_actions, horizon,
                                        reward_offset=reward_offset, check_simplex=check_simplex,
                                        dtype=dtype)
