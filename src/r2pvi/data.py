"""Offline datasets of K trajectories of length H with linear features.

The data model is feature-first: what every algorithm needs from a transition
``(s_h, a_h, r_h, s_{h+1})`` is the feature vector of the taken action ``phi(s_h, a_h)``,
the reward, and the features of *every* action at the next state ``phi(s_{h+1}, a')``,
from which the next step's value ``max_a' Q_{h+1}(s_{h+1}, a')`` is computed.
Next-state actions whose value is known (an absorbing fail state, a stopping action
with a known payoff) carry that value in ``next_values``; NaN means "learn it".
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from ._io import file_error, load_npz, save_npz
from ._validation import as_float_array, as_index_array

__all__ = ["OfflineDataset", "SimplexFeatureWarning", "check_simplex_features"]

DATASET_FORMAT_VERSION = 1


class SimplexFeatureWarning(UserWarning):
    """Features break the paper's simplex assumption (phi_i >= 0 and sum_i phi_i = 1)."""


def check_simplex_features(phi: np.ndarray, name: str = "phi", atol: float = 1e-8) -> bool:
    """Warn (do not fail) when feature rows leave the probability simplex.

    Returns True when every row of ``phi`` (last axis = features) is on the simplex.
    The d-rectangular theory assumes simplex features; the algorithms run on any
    features (the American put option's features break the assumption on purpose).
    """
    if phi.size == 0:
        return True
    negative = bool((phi < -atol).any())
    off_sum = bool((np.abs(phi.sum(axis=-1) - 1.0) > 1e-6).any())
    if negative or off_sum:
        what = " and ".join(
            w for w, bad in (("negative entries", negative), ("rows not summing to 1", off_sum))
            if bad
        )
        warnings.warn(
            f"{name} has {what}: the paper's simplex assumption (phi_i >= 0, sum_i phi_i = 1) "
            "does not hold. The algorithms still run; the d-rectangular guarantees do not apply.",
            SimplexFeatureWarning,
            stacklevel=3,
        )
        return False
    return True


class OfflineDataset:
    """K trajectories of length H, as features of taken and next-state actions.

    Build it with :meth:`from_features` or :meth:`from_transitions`; do not call the
    constructor directly. Arrays are stored step-major internally (the engine reads one
    step at a time) and exposed trajectory-major, as the constructors take them.

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

    def __init__(self, *, _phi, _rewards, _next_phi, _next_values, _extras=None):
        # Private: the public constructors validate and hand over step-major copies.
        self._phi = _phi  # (H, K, d)
        self._rewards = _rewards  # (H, K)
        self._next_phi = _next_phi  # (H, K, A, d)
        self._next_values = _next_values  # (H, K, A) or None when no value is known
        self._extras = dict(_extras or {})
        self._nonnegative: bool | None = None
        self._nonnegative_phi: bool | None = None

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_features(
        cls, phi, rewards, next_phi, next_values=None, *, check_simplex: bool = True,
        states=None, actions=None, next_states=None,
    ) -> OfflineDataset:
        """Build a dataset from feature arrays.

        Parameters
        ----------
        phi : array_like (K, H, d)
            Features of the taken actions.
        rewards : array_like (K, H)
            Observed rewards.
        next_phi : array_like (K, H, A, d)
            Features of every action at the next state; row ``h = H-1`` is ignored and
            may hold anything, NaN included.
        next_values : array_like (K, H, A), optional
            Known next-state action values, NaN where the value must be learned.
        check_simplex : bool, default True
            Warn with :class:`SimplexFeatureWarning` when features leave the simplex.
        states, actions, next_states : array_like (K, H, ...), optional
            The observed states, action indices and next states behind the features, kept as
            ``ds.states``, ``ds.actions``, ``ds.next_states`` (saved, subset with the data);
            for features that :meth:`from_transitions` cannot express (step-dependent ones).

        Returns
        -------
        OfflineDataset
        """
        phi = as_float_array(phi, "phi", ndim=3)
        K, H, d = phi.shape
        if K == 0:
            raise ValueError("phi has K = 0 trajectories; a dataset needs at least one")
        if H == 0 or d == 0:
            raise ValueError(f"phi must have H >= 1 steps and d >= 1 features, got {phi.shape}")
        rewards = as_float_array(rewards, "rewards", ndim=2)
        if rewards.shape != (K, H):
            raise ValueError(
                f"rewards must have shape (K, H) = {(K, H)} to match phi, got {rewards.shape}"
            )
        next_phi = as_float_array(next_phi, "next_phi", ndim=4, allow_nan=True)
        if next_phi.shape[:2] != (K, H) or next_phi.shape[3] != d:
            raise ValueError(
                f"next_phi must have shape (K, H, A, d) = ({K}, {H}, A, {d}), got {next_phi.shape}"
            )
        A = next_phi.shape[2]
        if A == 0:
            raise ValueError("next_phi has A = 0 actions; at least one action is needed")
        used = next_phi[:, : H - 1]
        if not np.isfinite(used).all():
            raise ValueError(
                "next_phi contains NaN or infinite entries in steps h < H-1 (only the last "
                "step's row may be left undefined)"
            )
        next_phi[:, H - 1] = np.where(np.isfinite(next_phi[:, H - 1]), next_phi[:, H - 1], 0.0)
        nv = None
        if next_values is not None:
            nv = as_float_array(next_values, "next_values", ndim=3, allow_nan=True)
            if nv.shape != (K, H, A):
                raise ValueError(
                    f"next_values must have shape (K, H, A) = {(K, H, A)}, got {nv.shape}; "
                    "use NaN where the value must be learned"
                )
            nv[:, H - 1] = np.nan
            if np.isnan(nv).all():
                nv = None
        if check_simplex:
            check_simplex_features(phi, "phi")
            check_simplex_features(used, "next_phi")
        extras = {}
        for name, value in (("states", states), ("actions", actions),
                            ("next_states", next_states)):
            if value is None:
                continue
            arr = np.asarray(value)
            if arr.shape[:2] != (K, H):
                raise ValueError(f"{name} must start with (K, H) = {(K, H)}, got {arr.shape}")
            if name == "actions":
                arr = as_index_array(arr, "actions", A, ndim=2)
            # A private, read-only copy: the caller's array is neither shared nor mutable here.
            extras[name] = _readonly(np.array(arr, copy=True))
        return cls(
            _phi=np.ascontiguousarray(phi.transpose(1, 0, 2)),
            _rewards=np.ascontiguousarray(rewards.T),
            _next_phi=np.ascontiguousarray(next_phi.transpose(1, 0, 2, 3)),
            _next_values=None if nv is None else np.ascontiguousarray(nv.transpose(1, 0, 2)),
            _extras=extras,
        )

    @classmethod
    def from_transitions(
        cls,
        states,
        actions,
        rewards,
        next_states,
        feature_map: Callable[[np.ndarray, np.ndarray], np.ndarray],
        n_actions: int,
        next_values=None,
        *,
        check_simplex: bool = True,
    ) -> OfflineDataset:
        """Build a dataset from observed states and actions and a vectorized feature map.

        Parameters
        ----------
        states, next_states : array_like (K, H, ...)
            Observed states ``s_h`` and ``s_{h+1}`` (any trailing shape: integer indices,
            prices, vectors).
        actions : array_like of int (K, H)
            Taken actions, indices in ``[0, n_actions)``.
        rewards : array_like (K, H)
        feature_map : callable
            ``feature_map(states, actions) -> (n, d)`` for ``states`` of shape ``(n, ...)``
            and integer ``actions`` of shape ``(n,)``; it is called once for the taken
            actions and once per action for the next states.
        n_actions : int
            Number of actions A.
        next_values : array_like (K, H, A) or callable, optional
            Known next-state action values (NaN: learn), or ``next_values(next_states)``
            returning ``(n, A)`` for ``next_states`` of shape ``(n, ...)``.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> onehot = lambda s, a: np.eye(4)[2 * s + a]       # 2 states x 2 actions
        >>> s = np.array([[0, 1]]); a = np.array([[1, 0]])
        >>> ds = OfflineDataset.from_transitions(s, a, [[0.0, 1.0]], [[1, 0]], onehot, 2)
        >>> ds.phi[0, 0], ds.next_phi[0, 0, 1]
        (array([0., 1., 0., 0.]), array([0., 0., 0., 1.]))
        """
        if not callable(feature_map):
            raise TypeError("feature_map must be callable: feature_map(states, actions) -> (n, d)")
        if isinstance(n_actions, bool) or not isinstance(n_actions, int | np.integer):
            raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
        if n_actions < 1:
            raise ValueError(f"n_actions must be >= 1, got {n_actions}")
        states = np.asarray(states)
        next_states = np.asarray(next_states)
        actions_arr = np.asarray(actions)
        if actions_arr.ndim != 2:
            raise ValueError(f"actions must have shape (K, H), got {actions_arr.shape}")
        actions_arr = as_index_array(actions_arr, "actions", int(n_actions), ndim=2)
        K, H = actions_arr.shape
        if states.shape[:2] != (K, H) or next_states.shape[:2] != (K, H):
            raise ValueError(
                f"states and next_states must start with (K, H) = {(K, H)} like actions, got "
                f"{states.shape} and {next_states.shape}"
            )
        if ((actions_arr < 0) | (actions_arr >= n_actions)).any():
            raise ValueError(f"actions must lie in [0, {n_actions}); got values outside")
        flat_s = states.reshape((K * H,) + states.shape[2:])
        flat_ns = next_states.reshape((K * H,) + next_states.shape[2:])
        phi = np.asarray(feature_map(flat_s, actions_arr.reshape(-1)), dtype=float)
        if phi.ndim != 2 or phi.shape[0] != K * H:
            raise ValueError(f"feature_map must return (n, d) = ({K * H}, d), got {phi.shape}")
        d = phi.shape[1]
        next_phi = np.empty((K * H, n_actions, d))
        for a in range(n_actions):
            out = np.asarray(feature_map(flat_ns, np.full(K * H, a)), dtype=float)
            if out.shape != (K * H, d):
                raise ValueError(f"feature_map returned shape {out.shape} for the next states")
            next_phi[:, a] = out
        if callable(next_values):
            nv = np.asarray(next_values(flat_ns), dtype=float)
            if nv.shape != (K * H, n_actions):
                raise ValueError(
                    f"next_values(next_states) must return (n, A) = {(K * H, n_actions)}, "
                    f"got {nv.shape}"
                )
            next_values = nv.reshape(K, H, n_actions)
        return cls.from_features(
            phi.reshape(K, H, d),
            rewards,
            next_phi.reshape(K, H, n_actions, d),
            next_values,
            check_simplex=check_simplex,
            states=states,
            actions=actions_arr,
            next_states=next_states,
        )

    @classmethod
    def from_episodes(cls, episodes, feature_map, n_actions: int, horizon: int | None = None,
                      *, reward_offset=None, check_simplex: bool = True) -> OfflineDataset:
        """Build a dataset from episodes of any length (Gymnasium rollouts, Minari datasets).

        Parameters
        ----------
        episodes : minari.MinariDataset or iterable
            Episodes with Minari's ``EpisodeData`` fields (objects or dicts):
            ``observations (T+1, ...)``, ``actions (T,)``, ``rewards (T,)``,
            ``terminations (T,)``, ``truncations (T,)``.
        feature_map : callable or fitted transformer
            ``feature_map(observations, actions) -> (n, d)`` (e.g.
            ``r2pvi.features.cross_actions(NormalizedRBF().fit(obs), n_actions)``), or a
            fitted observation transformer, crossed with the actions block-wise.
        n_actions : int
            Number of discrete actions A.
        horizon : int, optional
            H; None takes the longest episode. Longer episodes are cut at H.
        reward_offset : None, "auto" or float
            Negative rewards are refused unless shifted by ``reward_offset`` (an exact
            shift: the same greedy policy; see :mod:`r2pvi.episodes`).
        check_simplex : bool, default True

        A terminated episode continues in an absorbing state of known value 0; a truncated
        one ends without a terminal value; steps after an episode's end carry zero features
        (no data). Details: :mod:`r2pvi.episodes`.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> from r2pvi.features import StateAggregation, cross_actions
        >>> ep = {"observations": [[0.0], [0.4], [0.9]], "actions": [1, 0],
        ...       "rewards": [1.0, 1.0], "terminations": [False, True],
        ...       "truncations": [False, False]}
        >>> fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), 2)
        >>> ds = OfflineDataset.from_episodes([ep], fmap, n_actions=2, horizon=3)
        >>> ds.phi[0].tolist()                     # two steps, then no data
        [[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]
        >>> ds.next_values[0, 1].tolist()          # terminated: absorbing, value 0
        [0.0, 0.0]
        """
        from .episodes import dataset_from_episodes

        return dataset_from_episodes(episodes, feature_map, n_actions, horizon,
                                     reward_offset=reward_offset, check_simplex=check_simplex)

    # ------------------------------------------------------------------ views
    @property
    def n_trajectories(self) -> int:
        """K, the number of trajectories."""
        return self._phi.shape[1]

    @property
    def horizon(self) -> int:
        """H, the number of steps."""
        return self._phi.shape[0]

    @property
    def n_features(self) -> int:
        """d, the feature dimension."""
        return self._phi.shape[2]

    @property
    def n_actions(self) -> int:
        """A, the number of actions at the next states."""
        return self._next_phi.shape[2]

    @property
    def phi(self) -> np.ndarray:
        """Features of the taken actions, (K, H, d) (a read-only view)."""
        return _readonly(self._phi.transpose(1, 0, 2))

    @property
    def rewards(self) -> np.ndarray:
        """Rewards, (K, H) (a read-only view)."""
        return _readonly(self._rewards.T)

    @property
    def next_phi(self) -> np.ndarray:
        """Features of every next-state action, (K, H, A, d) (a read-only view)."""
        return _readonly(self._next_phi.transpose(1, 0, 2, 3))

    @property
    def next_values(self) -> np.ndarray:
        """Known next-state action values, (K, H, A), NaN where learned."""
        if self._next_values is None:
            return np.full((self.n_trajectories, self.horizon, self.n_actions), np.nan)
        return _readonly(self._next_values.transpose(1, 0, 2))

    @property
    def nonnegative_next_features(self) -> bool:
        """Whether every next-state feature is >= 0 (computed once, then cached)."""
        if self._nonnegative is None:
            self._nonnegative = bool((self._next_phi >= 0).all())
        return self._nonnegative

    @property
    def nonnegative_features(self) -> bool:
        """Whether every taken-action feature is >= 0 (computed once, then cached)."""
        if self._nonnegative_phi is None:
            self._nonnegative_phi = bool((self._phi >= 0).all())
        return self._nonnegative_phi

    @property
    def has_known_values(self) -> bool:
        """Whether any next-state action value is given."""
        return self._next_values is not None

    @property
    def states(self):
        """Observed states (K, H, ...) when built by :meth:`from_transitions`, else None."""
        return self._extras.get("states")

    @property
    def actions(self):
        """Taken action indices (K, H) when built by :meth:`from_transitions`, else None."""
        return self._extras.get("actions")

    @property
    def next_states(self):
        """Observed next states (K, H, ...) when built by :meth:`from_transitions`, else None."""
        return self._extras.get("next_states")

    def step(self, h: int):
        """Step-``h`` arrays ``(phi (K,d), rewards (K,), next_phi (K,A,d), next_values)``.

        ``next_values`` is ``(K, A)`` with NaN where learned, or None if none is known.
        ``h`` is 0-based.
        """
        nv = None if self._next_values is None else self._next_values[h]
        return self._phi[h], self._rewards[h], self._next_phi[h], nv

    def subset(self, indices) -> OfflineDataset:
        """The dataset restricted to the trajectories ``indices`` (for bootstraps, splits)."""
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
        extras = {k: _readonly(v[idx]) for k, v in self._extras.items()}
        return OfflineDataset(
            _phi=np.ascontiguousarray(self._phi[:, idx]),
            _rewards=np.ascontiguousarray(self._rewards[:, idx]),
            _next_phi=np.ascontiguousarray(self._next_phi[:, idx]),
            _next_values=None
            if self._next_values is None
            else np.ascontiguousarray(self._next_values[:, idx]),
            _extras=extras,
        )

    def __repr__(self) -> str:
        return (
            f"OfflineDataset(K={self.n_trajectories}, H={self.horizon}, d={self.n_features}, "
            f"A={self.n_actions}, known_values={self.has_known_values})"
        )

    # ------------------------------------------------------------------ I/O
    def save(self, path):
        """Save to a versioned ``.npz`` file (no pickle); returns the path written.

        Examples
        --------
        >>> import numpy as np, tempfile, os
        >>> from r2pvi import OfflineDataset
        >>> ds = OfflineDataset.from_features(np.ones((2, 1, 1)), np.zeros((2, 1)),
        ...                                   np.ones((2, 1, 1, 1)))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     p = ds.save(os.path.join(tmp, "data.npz"))
        ...     OfflineDataset.load(p).n_trajectories
        2
        """
        arrays = {
            "phi": self.phi,
            "rewards": self.rewards,
            "next_phi": self.next_phi,
            "next_values": self.next_values,
        }
        for key, value in self._extras.items():
            value = np.asarray(value)
            if value.dtype == object:
                raise TypeError(f"cannot save {key!r}: object arrays are not supported")
            arrays["extra_" + key] = value
        return save_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION, arrays, {})

    @classmethod
    def load(cls, path) -> OfflineDataset:
        """Load a dataset written by :meth:`save`."""
        arrays, _ = load_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION)
        known = {"phi", "rewards", "next_phi", "next_values"}
        known |= {"extra_" + k for k in ("states", "actions", "next_states")}
        for name in sorted(known - set(arrays)):
            if not name.startswith("extra_"):
                raise file_error(path, name, "is missing")
        unknown = sorted(set(arrays) - known)
        if unknown:
            raise file_error(path, unknown[0], "is not a field of an OfflineDataset file")
        extras = {k[len("extra_") :]: v for k, v in arrays.items() if k.startswith("extra_")}
        try:  # the loaded arrays go through the same checks as from_features
            return cls.from_features(
                arrays["phi"],
                arrays["rewards"],
                arrays["next_phi"],
                arrays["next_values"],
                check_simplex=False,
                **extras,
            )
        except (TypeError, ValueError) as exc:
            raise file_error(path, None, f"holds invalid data: {exc}") from None


def _readonly(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v
