"""Offline datasets of K trajectories of length H with linear features.

The data model is feature-first: what every algorithm needs from a transition
``(s_h, a_h, r_h, s_{h+1})`` is the feature vector of the taken action ``phi(s_h, a_h)``,
the reward, and the features of *every* action at the next state ``phi(s_{h+1}, a')``,
from which the next step's value ``max_a' Q_{h+1}(s_{h+1}, a')`` is computed.
Next-state actions whose value is known (an absorbing fail state, a stopping action
with a known payoff) carry that value in ``next_values``; NaN means "learn it".

The numbers live in a step-major :class:`~r2pvi.storage.StepSource` (in memory, in a
dataset directory on disk, or in Dask arrays); see :mod:`r2pvi.storage`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .._io import file_error, load_npz, save_npz
from .._validation import as_array, as_float_array, as_index_array
from . import storage as _st
from .storage import SimplexFeatureWarning
from .storage.behaviour import _next_form
from .storage.fields import _float_dtype

__all__ = ["OfflineDataset", "SimplexFeatureWarning", "check_simplex_features"]

DATASET_FORMAT_VERSION = 1  # the legacy single-file .npz format (still read and written)


def check_simplex_features(phi: np.ndarray, name: str = "phi", atol: float = 1e-8) -> bool:
    """Warn (do not fail) when feature rows leave the probability simplex.

    Returns True when every row of ``phi`` (last axis = features) is on the simplex.
    The d-rectangular theory assumes simplex features; the algorithms run on any
    features (the American put option's features break the assumption on purpose).
    """
    neg, off = _st.simplex_flags(np.asarray(phi), atol)
    return _st.warn_simplex(name, neg, off, stacklevel=3)


class OfflineDataset:
    """K trajectories of length H, as features of taken and next-state actions.

    Build it with :meth:`from_features`, :meth:`from_transitions`,
    :meth:`from_next_state_table`, :meth:`from_dask`, or open a dataset directory with
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

    def __init__(self, *, _phi=None, _rewards=None, _next_phi=None, _next_values=None,
                 _extras=None, _source=None):
        # Private: the public constructors validate and hand over a step source (or, as
        # before, step-major arrays: phi (H, K, d), rewards (H, K), next_phi (H, K, A, d),
        # next_values (H, K, A) or None).
        if _source is None:
            nv = None if _next_values is None else _st.ArrayField(_next_values)
            _source = _st.StepSource(
                _st.ArrayField(_phi), _st.ArrayField(_rewards),
                _st.StoredNext(_st.ArrayField(_next_phi), nv), _extras)
        self._source = _source
        self._nonnegative: bool | None = _source.next.nonnegative
        self._nonnegative_phi: bool | None = _source.nonnegative_phi

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_features(
        cls, phi, rewards, next_phi, next_values=None, *, check_simplex: bool = True,
        states=None, actions=None, next_states=None, dtype=None, reward_noise=0.0,
    ) -> OfflineDataset:
        """Build a dataset from feature arrays.

        At most one copy is made (to step-major float storage), and none when the arrays
        already are step-major floats: ``a.transpose(1, 0, ...)`` of a C-contiguous
        ``(H, K, ...)`` float32/float64 array (such as ``ds.phi`` of another dataset). Then
        the dataset keeps a read-only view of the caller's memory: do not modify it later.
        Validation runs chunk by chunk, without full-size temporaries.

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
        dtype : {None, "float32", "float64"}, default None
            Storage type of the features: None keeps float32 or float64 input as it is (other
            numbers become float64). Fitting accumulates in float64 either way.
        reward_noise : float, default 0.0
            Standard deviation of zero-mean noise on the observed rewards, when they are
            noisy samples of mean rewards in ``[0, r_max]`` (``FiniteLinearMDP`` with
            ``reward_noise > 0``, the lower bound's hard instances): ``fit`` then lets samples
            leave ``[0, r_max]`` by up to ``REWARD_NOISE_Z = 8`` standard deviations (see
            :attr:`reward_noise`).

        Returns
        -------
        OfflineDataset

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> phi_sm = np.full((2, 5, 3), 1 / 3)                 # step-major (H, K, d)
        >>> ds = OfflineDataset.from_features(phi_sm.transpose(1, 0, 2), np.zeros((5, 2)),
        ...                                   np.full((5, 2, 2, 3), 1 / 3))
        >>> np.shares_memory(ds.phi, phi_sm)                   # no copy was made
        True
        """
        dtype = None if dtype is None else _float_dtype(dtype)
        p = _st.step_major(phi, "phi", 3, dtype)
        H, K, d = p.shape
        if K == 0:
            raise ValueError("phi has K = 0 trajectories; a dataset needs at least one")
        if H == 0 or d == 0:
            raise ValueError(f"phi must have H >= 1 steps and d >= 1 features, got {(K, H, d)}")
        r = _st.step_major(rewards, "rewards", 2, np.float64)
        if r.shape != (H, K):
            raise ValueError(
                f"rewards must have shape (K, H) = {(K, H)} to match phi, got {np.shape(rewards)}"
            )
        n = _st.step_major(next_phi, "next_phi", 4, dtype or p.dtype)
        if n.shape[:2] != (H, K) or n.shape[3] != d:
            raise ValueError(
                f"next_phi must have shape (K, H, A, d) = ({K}, {H}, A, {d}), got "
                f"{np.shape(next_phi)}"
            )
        A = n.shape[2]
        if A == 0:
            raise ValueError("next_phi has A = 0 actions; at least one action is needed")
        nv = None
        if next_values is not None:
            nv = _st.step_major(next_values, "next_values", 3, np.float64)
            if nv.shape != (H, K, A):
                raise ValueError(
                    f"next_values must have shape (K, H, A) = {(K, H, A)}, got "
                    f"{np.shape(next_values)}; use NaN where the value must be learned"
                )
        nonneg_phi, nonneg_next, any_known, unit, reward_range, row_sums = _st.validate_source(
            p, r, n, nv, check_simplex, stacklevel=3)
        extras = _check_extras(K, H, A, states=states, actions=actions, next_states=next_states)
        known = _st.ArrayField(nv) if nv is not None and any_known else None
        source = _st.StepSource(_st.ArrayField(p), _st.ArrayField(r),
                                _st.StoredNext(_st.ArrayField(n), known, nonneg_next),
                                extras, nonneg_phi, unit_rows=unit,
                                reward_range=reward_range, row_sums=row_sums,
                                reward_noise=_st.check_reward_noise(reward_noise),
                                checked=("phi", "rewards", "next"))
        return cls(_source=source)

    @classmethod
    def from_next_state_table(
        cls, phi, rewards, next_states, table, known_values=None, *, check_simplex=True,
        states=None, actions=None, dtype=None, reward_noise=0.0,
    ) -> OfflineDataset:
        """Build a dataset whose next states index a feature table (finite state spaces).

        Nothing per sample is stored for the next states but their index: the engine
        computes ``V_{h+1}`` once per state of the table and gathers it by index.

        Parameters
        ----------
        phi : array_like (K, H, d)
            Features of the taken actions.
        rewards : array_like (K, H)
        next_states : array_like of int (K, H)
            Next-state indices into ``table`` (row ``h = H-1`` is never used).
        table : array_like (S, A, d) or (H, S, A, d)
            Features of every action at every state; a 4-D table gives step-dependent
            features, row ``h`` being those of the next states of step ``h`` (for a finite
            MDP with features ``phi_h``: ``table[h] = phi_{h+1}``).
        known_values : array_like (S, A), optional
            Known action values by next state (NaN: learn), e.g. 0 at absorbing fail states.
        check_simplex, states, actions, dtype, reward_noise
            As in :meth:`from_features`.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> table = np.array([[[1.0, 0.0], [0.5, 0.5]], [[0.0, 1.0], [0.0, 1.0]]])  # S=2, A=2
        >>> ds = OfflineDataset.from_next_state_table(
        ...     table[[[0, 1]], [[1, 0]]], [[0.0, 1.0]], [[1, 1]], table)
        >>> ds.next_phi[0, 0].tolist()
        [[0.0, 1.0], [0.0, 1.0]]
        """

        dtype = None if dtype is None else _float_dtype(dtype)
        p = _st.step_major(phi, "phi", 3, dtype)
        H, K, d = p.shape
        if K == 0 or H == 0 or d == 0:
            raise ValueError(f"phi must have K, H, d >= 1, got {(K, H, d)}")
        r = _st.step_major(rewards, "rewards", 2, np.float64)
        if r.shape != (H, K):
            raise ValueError(f"rewards must have shape (K, H) = {(K, H)}, got {np.shape(rewards)}")
        tab = as_float_array(table, "table")
        if tab.ndim not in (3, 4) or tab.shape[-1] != d or (tab.ndim == 4 and tab.shape[0] != H):
            raise ValueError(
                f"table must have shape (S, A, d) or (H, S, A, d) with H = {H}, d = {d}, "
                f"got {tab.shape}")
        S, A = tab.shape[-3], tab.shape[-2]
        idx = as_array(next_states, "next_states")
        if idx.shape != (K, H):
            raise ValueError(f"next_states must have shape (K, H) = {(K, H)}, got {idx.shape}")
        if not np.issubdtype(idx.dtype, np.integer):
            if np.issubdtype(idx.dtype, np.floating) and np.all(idx == np.round(idx)):
                idx = idx.astype(np.int64)
            else:
                raise TypeError("next_states must be integer state indices into table")
        if idx.size and (idx.min() < 0 or idx.max() >= S):
            raise ValueError(f"next_states must lie in [0, {S}) (the table's states)")
        kt = None
        if known_values is not None:
            kt = as_float_array(known_values, "known_values", ndim=2, allow_nan=True)
            if kt.shape != (S, A):
                raise ValueError(f"known_values must have shape (S, A) = {(S, A)}, got {kt.shape}")
            if np.isnan(kt).all():
                kt = None
        nonneg_phi, _, _, unit, reward_range, row_sums = _st.validate_source(
            p, r, None, None, check_simplex, stacklevel=3)
        if check_simplex:
            used = tab if tab.ndim == 3 else tab[: max(H - 1, 1)]
            check_simplex_features(used, "table")
        ix = np.array(idx.T, order="C", copy=True)  # private, step-major; ix.T is the extra
        extras = _check_extras(K, H, A, _owned=("next_states",), states=states,
                               actions=actions, next_states=ix.T)
        source = _st.StepSource(_st.ArrayField(p), _st.ArrayField(r),
                                _st.TableNext(_st.ArrayField(ix), tab, kt), extras, nonneg_phi,
                                unit_rows=unit, reward_range=reward_range, row_sums=row_sums,
                                reward_noise=_st.check_reward_noise(reward_noise),
                                checked=("phi", "rewards", "next"))
        return cls(_source=source)

    @classmethod
    def from_observations(
        cls, states, actions, rewards, next_states, feature_map, n_actions: int,
        next_values=None, *, check_simplex: bool = True,
    ) -> OfflineDataset:
        """Stored observations and a feature map evaluated chunk by chunk while fitting.

        The arguments of :meth:`from_transitions`, but no feature is stored: the taken-action
        features ``feature_map(states[:, h], actions[:, h])`` and every action's features at
        the next states are computed a chunk of trajectories at a time, each step, and never
        held for the whole dataset (a step's ``(K, d)`` taken-action features are). Arrays
        (memory maps included) are kept as step-major views when they are laid out so, else
        copied once. :meth:`save` stores the observations; :meth:`open` then needs the same
        ``feature_map``. The rewards are checked here; the features, computed while fitting,
        by the fit (a ``feature_map`` that returns NaN or an infinity is a ``ValueError``
        naming the step, trajectory and feature).

        Parameters
        ----------
        states, next_states : array_like (K, H, ...)
            Observations ``s_h`` and ``s_{h+1}`` (row ``h = H-1`` of ``next_states`` is never
            used).
        actions : array_like of int (K, H)
            Taken actions, indices in ``[0, n_actions)``.
        rewards : array_like (K, H)
        feature_map : callable
            ``feature_map(observations (n, ...), actions (n,)) -> (n, d)``.
        n_actions : int
        next_values : callable, optional
            ``next_values(next_states (n, ...)) -> (n, A)``, known action values (NaN: learn).
        check_simplex : bool, default True
            Warn when the features of the first chunk of trajectories leave the simplex.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import OfflineDataset
        >>> fmap = lambda x, a: np.stack([x[:, 0] * (a == 0), x[:, 0] * (a == 1),
        ...                               1 - x[:, 0]], axis=1)
        >>> rng = np.random.default_rng(0)
        >>> obs, nxt = rng.random((20, 3, 1)), rng.random((20, 3, 1))
        >>> ds = OfflineDataset.from_observations(obs, rng.integers(2, size=(20, 3)),
        ...                                       rng.random((20, 3)), nxt, fmap, 2)
        >>> ds.phi.shape, ds.next_phi.shape
        ((20, 3, 3), (20, 3, 2, 3))
        """
        _check_feature_map(feature_map, n_actions)
        if next_values is not None and not callable(next_values):
            raise TypeError("next_values must be callable: next_values(next_states) -> (n, A)")
        act = as_array(actions, "actions")
        if act.ndim != 2:
            raise ValueError(f"actions must have shape (K, H), got {act.shape}")
        if not np.issubdtype(act.dtype, np.integer):
            raise TypeError(f"actions must be integer action indices, got dtype {act.dtype}")
        K, H = act.shape
        if K == 0 or H == 0:
            raise ValueError(f"actions must have K >= 1 and H >= 1, got {act.shape}")
        obs, nobs = as_array(states, "states"), as_array(next_states, "next_states")
        if obs.shape[:2] != (K, H) or nobs.shape[:2] != (K, H):
            raise ValueError(
                f"states and next_states must start with (K, H) = {(K, H)} like actions, got "
                f"{obs.shape} and {nobs.shape}")
        r = _st.step_major(rewards, "rewards", 2, np.float64)
        if r.shape != (H, K):
            raise ValueError(f"rewards must have shape (K, H) = {(K, H)}, got {np.shape(rewards)}")
        if not all(np.isfinite(r[h]).all() for h in range(H)):
            raise ValueError("rewards contains NaN or infinite entries; clean the data first")
        sm = [_st.ArrayField(_st.layout_step_major(x)) for x in (obs, act, nobs)]
        for name, field in (("states", sm[0]), ("next_states", sm[2])):
            _check_finite_observations(field, name, H)
        for h in range(H):
            for _, _, rows in sm[1].chunks(h, _st.CHUNK):
                if rows.size and (rows.min() < 0 or rows.max() >= n_actions):
                    raise ValueError(f"actions must lie in [0, {n_actions}); got values outside")
        probe = np.asarray(feature_map(sm[0].read(0, 0, 1), sm[1].read(0, 0, 1).astype(np.int64)))
        if probe.ndim != 2 or probe.shape[0] != 1 or probe.shape[1] < 1:
            raise ValueError(f"feature_map must return (n, d) for n observations, got "
                             f"{probe.shape} for one")
        d = probe.shape[1]
        phi = _st.MappedField(sm[0], sm[1], feature_map, d)
        nxt = _st.MapNext(sm[2], feature_map, int(n_actions), d, next_values)
        if check_simplex:
            first = phi.read(0, 0, _st.CHUNK)
            check_simplex_features(first, "phi")
            if H > 1:
                check_simplex_features(nxt.features(0, 0, _st.CHUNK), "next_phi")
        # the rewards are checked here; the features, computed while fitting, by the fit
        return cls(_source=_st.StepSource(phi, _st.ArrayField(r), nxt, {},
                                          reward_range=(float(r.min()), float(r.max())),
                                          checked=("rewards",)))

    @classmethod
    def from_dask(cls, phi, rewards, next_phi, next_values=None) -> OfflineDataset:
        """A dataset held as Dask arrays, chunked along trajectories (the ``dask`` extra).

        Takes the shapes of :meth:`from_features` (``phi (K, H, d)``, ...) as Dask arrays;
        nothing is computed here. Fitting reads one step at a time: the next-state values are
        computed on the workers, chunk by chunk, and only a step's ``(K, d)`` features and
        ``K`` values come back. Nothing is checked here: a fit checks every number it uses
        as it reads it (finite; rewards in ``[0, r_max]``) and names the first bad entry
        (step, trajectory, feature). Fits equal the in-memory fits to rounding.
        """
        try:
            import dask.array as da
        except ImportError as exc:  # pragma: no cover - the extra is installed in CI
            raise ImportError("OfflineDataset.from_dask needs the 'dask' extra: "
                              "pip install 'r2pvi[dask]'") from exc
        arrays = [phi, rewards, next_phi] + ([] if next_values is None else [next_values])
        for name, a, nd in zip(("phi", "rewards", "next_phi", "next_values"), arrays,
                               (3, 2, 4, 3), strict=False):
            if not isinstance(a, da.Array):
                raise TypeError(f"{name} must be a dask.array.Array, got {type(a).__name__}")
            if a.ndim != nd:
                raise ValueError(f"{name} must have {nd} dimensions, got shape {a.shape}")
        K, H, d = phi.shape
        if rewards.shape != (K, H) or next_phi.shape[:2] != (K, H) or next_phi.shape[3] != d:
            raise ValueError("rewards (K, H) and next_phi (K, H, A, d) must match phi (K, H, d)")
        if next_values is not None and next_values.shape != next_phi.shape[:3]:
            raise ValueError("next_values must have shape (K, H, A)")
        chunks = phi.chunks[0]

        def sm(a):  # step-major, chunked along trajectories like phi, whole on other axes
            a = a.rechunk((chunks,) + tuple(-1 for _ in a.shape[1:]))
            return a.swapaxes(0, 1)

        nv = None if next_values is None else _st.DaskField(sm(next_values))
        source = _st.StepSource(_st.DaskField(sm(phi)), _st.DaskField(sm(rewards)),
                                _st.StoredNext(_st.DaskField(sm(next_phi)), nv))
        return cls(_source=source)

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
        _check_feature_map(feature_map, n_actions)
        states = as_array(states, "states")
        next_states = as_array(next_states, "next_states")
        actions_arr = as_array(actions, "actions")
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

        _check_map_actions(feature_map, n_actions)
        return dataset_from_episodes(episodes, feature_map, n_actions, horizon,
                                     reward_offset=reward_offset, check_simplex=check_simplex)

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
        """Where the data lives: ``"memory"``, ``"disk"`` or ``"dask"``."""
        f = self._source.phi
        return "disk" if isinstance(f, _st.FileField) else (
            "dask" if isinstance(f, _st.DaskField) else "memory")

    @property
    def phi(self) -> np.ndarray:
        """Features of the taken actions, (K, H, d) (a read-only view; a memory map on disk)."""
        return _readonly(self._source.phi.lazy().swapaxes(0, 1))

    @property
    def rewards(self) -> np.ndarray:
        """Rewards, (K, H) (a read-only view)."""
        return _readonly(self._source.rewards.lazy().swapaxes(0, 1))

    @property
    def next_phi(self) -> np.ndarray:
        """Features of every next-state action, (K, H, A, d) (a read-only view when stored;
        computed, and so materialized, when they come from a table or a feature map)."""
        nxt = self._source.next
        if isinstance(nxt, _st.StoredNext):
            return _readonly(nxt.next_phi.lazy().swapaxes(0, 1))
        out = np.stack([nxt.features(h) for h in range(self.horizon)], axis=1)
        return _readonly(out)

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
            nxt = self._source.next
            self._nonnegative = all(
                bool((nxt.features(h, s, min(s + self._source.chunk, self.n_trajectories))
                      >= 0).all())
                for h in range(self.horizon - 1)
                for s in range(0, self.n_trajectories, self._source.chunk)
            )
        return self._nonnegative

    @property
    def nonnegative_features(self) -> bool:
        """Whether every taken-action feature is >= 0 (computed once, then cached)."""
        if self._nonnegative_phi is None:
            self._nonnegative_phi = all(
                bool((rows >= 0).all()) for h in range(self.horizon)
                for _, _, rows in self._source.phi.chunks(h, self._source.chunk)
            )
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
        cached = getattr(self, "_reward_range", None)
        if cached is None:
            source = getattr(self, "_source", None)
            if source is not None:
                cached = source.reward_bounds()
            else:  # datasets that keep their rewards themselves (sparse rows): (K, H)
                r = np.asarray(self.rewards)
                cached = (float(r.min()), float(r.max()))
            self._reward_range = cached
        return cached

    @property
    def reward_noise(self) -> float:
        """Standard deviation of zero-mean noise on the observed rewards (0: exact rewards).

        Set by ``reward_noise=`` of :meth:`from_features` and :meth:`from_next_state_table`
        (``FiniteLinearMDP.collect`` passes its own); kept by :meth:`subset`, :meth:`save`
        and :meth:`open`. ``fit`` checks the rewards against ``[0, r_max]`` up to
        ``8 * reward_noise``: noisy samples of in-range mean rewards leave the range, a
        wrong reward scale does not hide in the noise."""
        source = getattr(self, "_source", None)
        return 0.0 if source is None else source.reward_noise

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

    def step(self, h: int):
        """Step-``h`` arrays ``(phi (K,d), rewards (K,), next_phi (K,A,d), next_values)``.

        ``next_values`` is ``(K, A)`` with NaN where learned, or None if none is known.
        ``h`` is 0-based. The whole step is read (the engine reads it in chunks instead).
        """
        src = self._source
        nv = src.next.known(h) if src.next.has_known_values else None
        return src.phi_step(h), src.rewards_step(h), src.next.features(h), nv

    def step_phi(self, h: int) -> np.ndarray:
        """Step ``h``'s taken-action features ``(K, d)`` in float64 (a view when stored so)."""
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
        in memory, whatever the storage."""
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

    def __repr__(self) -> str:
        return (
            f"OfflineDataset(K={self.n_trajectories}, H={self.horizon}, d={self.n_features}, "
            f"A={self.n_actions}, known_values={self.has_known_values})"
        )

    # ------------------------------------------------------------------ I/O
    def save(self, path, *, dtype=None, overwrite: bool = False,
             next_form: str = "full") -> Path:
        """Save in the on-disk format: a directory of step-major ``.npy`` files and a JSON
        manifest (format version 2), written in a temporary directory and renamed into
        place. A path ending in ``.npz`` writes the legacy single-file format (version 1),
        atomically too. An existing path is refused unless ``overwrite=True``, and then too
        unless it holds an r2pvi dataset (a dataset directory holding only its own files, a
        dataset ``.npz`` file) or nothing (an empty directory; an empty file for an ``.npz``
        path): a ``FileExistsError`` names what is there, so a save never destroys a file or
        directory r2pvi did not write. A failed save keeps the previous dataset. Returns the
        path written. Open it lazily with :meth:`open` (any size).

        ``next_form="behaviour"`` stores the next-state features without each sample's row
        that equals the next step's taken-action features ``phi[k, h+1]`` (see
        :class:`~r2pvi.DatasetWriter`); the fits are bitwise the same.

        Examples
        --------
        >>> import numpy as np, tempfile, os
        >>> from r2pvi import OfflineDataset
        >>> ds = OfflineDataset.from_features(np.ones((2, 1, 1)), np.zeros((2, 1)),
        ...                                   np.ones((2, 1, 1, 1)))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     p = ds.save(os.path.join(tmp, "data"))
        ...     sorted(os.listdir(p)), OfflineDataset.open(p).n_trajectories
        (['gram.npy', 'manifest.json', 'next_phi.npy', 'phi.npy', 'phi_sums.npy', 'rewards.npy'], 2)
        """
        p = Path(os.fspath(path))
        next_form = _next_form(next_form)
        if p.suffix == ".npz":
            if next_form != "full":
                raise ValueError("the legacy .npz format stores next_phi whole: use a "
                                 "directory path for next_form='behaviour'")
            return self._save_npz(p, overwrite)
        dtype = None if dtype is None else _float_dtype(dtype)
        return _st.write_directory(self._source, p, dtype=dtype, overwrite=overwrite,
                                   next_form=next_form)

    def _save_npz(self, path, overwrite: bool = False):
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
        meta = {"reward_noise": self.reward_noise} if self.reward_noise else {}
        return save_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION, arrays, meta,
                        overwrite=overwrite)

    @classmethod
    def open(cls, path, *, feature_map=None) -> OfflineDataset:
        """Open a dataset directory written by :meth:`save` or :class:`~r2pvi.DatasetWriter`
        lazily: only the headers are read; a fit reads one step at a time, in chunks.
        ``feature_map`` is needed (and only then) for a dataset stored as observations
        (see :meth:`from_observations`)."""
        return cls(_source=_st.open_directory(path, feature_map))

    @classmethod
    def load(cls, path) -> OfflineDataset:
        """Load a dataset written by :meth:`save` into memory: a directory (format 2) or a
        legacy ``.npz`` file (format 1)."""
        p = Path(os.fspath(path))
        if p.is_dir():
            src = _st.open_directory(p)
            return cls(_source=src.take(np.arange(src.n_trajectories)))
        arrays, header = load_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION)
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
                reward_noise=header.get("reward_noise", 0.0),
                **extras,
            )
        except (TypeError, ValueError) as exc:
            raise file_error(path, None, f"holds invalid data: {exc}") from None


def _check_extras(K, H, A, _owned=(), **given) -> dict:
    """Observed states, actions, next states: checked, kept private and read-only.

    ``_owned`` names arrays the dataset already owns (made here, never the caller's)."""
    extras = {}
    for name, value in given.items():
        if value is None:
            continue
        arr = np.asarray(value)
        if arr.shape[:2] != (K, H):
            raise ValueError(f"{name} must start with (K, H) = {(K, H)}, got {arr.shape}")
        owned = name in _owned
        if name == "actions":
            arr = as_index_array(arr, "actions", A, ndim=2)
            owned = True  # as_index_array returns a new array
        # A private, read-only copy: the caller's array is neither shared nor mutable here.
        extras[name] = _readonly(arr if owned else np.array(arr, copy=True))
    return extras


def _check_finite_observations(field, name: str, horizon: int) -> None:
    """Refuse NaN or infinite observations (a step at a time: memory maps stay unread but
    for one chunk), naming the step and trajectory: a feature map would turn them into
    features the fit cannot use, and the error would blame the map."""
    if field.dtype.kind != "f":
        return
    for h in range(horizon):
        for s, _, rows in field.chunks(h, _st.CHUNK):
            bad = ~np.isfinite(rows)
            if bad.any():
                k = s + int(np.argwhere(bad)[0][0])
                raise ValueError(f"{name} holds a non-finite value at step {h}, trajectory {k} "
                                 f"({name}[{k}, {h}]): clean the observations first")


def _readonly(a):
    if not isinstance(a, np.ndarray):
        return a  # a Dask array: immutable already
    v = a.view()
    v.flags.writeable = False
    return v


def _check_feature_map(feature_map, n_actions) -> None:
    """A callable ``feature_map(states, actions) -> (n, d)`` and an integer ``n_actions >= 1``."""
    if not callable(feature_map):
        raise TypeError("feature_map must be callable: feature_map(states, actions) -> (n, d)")
    if isinstance(n_actions, bool) or not isinstance(n_actions, int | np.integer):
        raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
    if n_actions < 1:
        raise ValueError(f"n_actions must be >= 1, got {n_actions}")
    _check_map_actions(feature_map, n_actions)


def _check_map_actions(feature_map, n_actions) -> None:
    """``n_actions`` agrees with a feature map that records its own (``cross_actions``)."""
    _st.check_map_actions(feature_map, n_actions)
