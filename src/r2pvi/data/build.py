"""The constructors of :class:`~r2pvi.OfflineDataset` from arrays, over one validation path.

Each constructor takes the class first (``OfflineDataset`` binds them as classmethods:
``OfflineDataset.from_features(...)``), validates its arguments (shapes, dtypes, the numbers:
finite, the simplex, non-negativity, the rewards' range) and hands the class a
:class:`~r2pvi.data.storage.StepSource`. :func:`features_and_rewards` is the path every
constructor of stored features takes; the constructors over observations and a feature map
are in :mod:`~r2pvi.data.build_observations`, those of sparse rows in
:mod:`~r2pvi.data.build_sparse`.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_array, as_float_array, as_index_array
from . import storage as _st
from .storage.fields import _float_dtype, readonly

__all__ = ["check_simplex_features", "from_features", "from_next_state_table", "from_dask"]


def check_simplex_features(phi: np.ndarray, name: str = "phi", atol: float = 1e-8) -> bool:
    """Warn (do not fail) when feature rows leave the probability simplex.

    Returns True when every row of ``phi`` (last axis = features) is on the simplex.
    The d-rectangular theory assumes simplex features; the algorithms run on any
    features (the American put option's features break the assumption on purpose).
    """
    neg, off = _st.simplex_flags(np.asarray(phi), atol)
    return _st.warn_simplex(name, neg, off, stacklevel=3)



def features_and_rewards(phi, rewards, dtype):
    """``(phi (H, K, d), rewards (H, K), dtype)`` step-major, with ``K, H, d >= 1`` and the
    rewards' shape checked (``dtype``: None keeps float32 or float64 features)."""
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
    return p, r, dtype


def from_features(
    cls, phi, rewards, next_phi, next_values=None, *, check_simplex: bool = True,
    states=None, actions=None, next_states=None, dtype=None, reward_noise=0.0,
):
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
    p, r, dtype = features_and_rewards(phi, rewards, dtype)
    H, K, d = p.shape
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



def from_next_state_table(
    cls, phi, rewards, next_states, table, known_values=None, *, check_simplex=True,
    states=None, actions=None, dtype=None, reward_noise=0.0,
):
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

    p, r, dtype = features_and_rewards(phi, rewards, dtype)
    H, K, d = p.shape
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



def from_dask(cls, phi, rewards, next_phi, next_values=None):
    """A dataset held as Dask arrays, chunked along trajectories (the ``dask`` extra).

    Takes the shapes of :meth:`from_features` (``phi (K, H, d)``, ...) as Dask arrays;
    nothing is computed here. What can be checked without computing is checked as
    :meth:`from_features` checks it: the types, dimensions and shapes (``K, H, d, A >= 1``,
    known chunk sizes), real-number dtypes (features of another real type are stored as
    float64, lazily). Fitting reads one step at a time: the next-state values are computed
    on the workers, chunk by chunk, and only a step's ``(K, d)`` features and ``K`` values
    come back; a fit checks every number it uses as it reads it (finite; rewards in
    ``[0, r_max]``) and names the first bad entry (step, trajectory, feature). Fits equal the
    in-memory fits to rounding.
    """
    try:
        import dask.array as da
    except ImportError as exc:  # pragma: no cover - the extra is installed in CI
        raise ImportError("OfflineDataset.from_dask needs the 'dask' extra: "
                          "pip install 'r2pvi[dask]'") from exc
    arrays = [phi, rewards, next_phi] + ([] if next_values is None else [next_values])
    for name, a, nd in zip(("phi", "rewards", "next_phi", "next_values"), arrays,
                           (3, 2, 4, 3), strict=False):
        _check_dask(a, name, nd, da)
    K, H, d = phi.shape
    if K == 0:
        raise ValueError("phi has K = 0 trajectories; a dataset needs at least one")
    if H == 0 or d == 0:
        raise ValueError(f"phi must have H >= 1 steps and d >= 1 features, got {(K, H, d)}")
    if rewards.shape != (K, H):
        raise ValueError(f"rewards must have shape (K, H) = {(K, H)} to match phi, got "
                         f"{rewards.shape}")
    if next_phi.shape[:2] != (K, H) or next_phi.shape[3] != d:
        raise ValueError(f"next_phi must have shape (K, H, A, d) = ({K}, {H}, A, {d}), got "
                         f"{next_phi.shape}")
    A = next_phi.shape[2]
    if A == 0:
        raise ValueError("next_phi has A = 0 actions; at least one action is needed")
    if next_values is not None and next_values.shape != (K, H, A):
        raise ValueError(f"next_values must have shape (K, H, A) = {(K, H, A)}, got "
                         f"{next_values.shape}; use NaN where the value must be learned")
    chunks = phi.chunks[0]

    def sm(a, features=False):  # step-major, chunked along trajectories like phi
        if features and a.dtype not in (np.float32, np.float64):
            a = a.astype(np.float64)  # as from_features stores other numbers (lazily)
        # one chunk per step: a step's rows are whole chunks (Dask copies a slice that is
        # less than half of its chunk: every step would copy its features)
        a = a.rechunk((chunks, 1) + tuple(-1 for _ in a.shape[2:]))
        return a.swapaxes(0, 1)

    nv = None if next_values is None else _st.DaskField(sm(next_values))
    source = _st.StepSource(_st.DaskField(sm(phi, True)), _st.DaskField(sm(rewards)),
                            _st.StoredNext(_st.DaskField(sm(next_phi, True)), nv))
    return cls(_source=source)


def _check_dask(a, name: str, ndim: int, da) -> None:
    """``a`` is a Dask array of real numbers with ``ndim`` dimensions and known chunk sizes
    (nothing is computed)."""
    if not isinstance(a, da.Array):
        raise TypeError(f"{name} must be a dask.array.Array, got {type(a).__name__}")
    kind = np.dtype(a.dtype).kind
    if kind == "c":
        raise TypeError(f"{name} must be real, got a complex Dask array")
    if kind not in "biuf":
        raise TypeError(f"{name} must be a numeric (float) Dask array, got dtype {a.dtype}")
    if a.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {a.shape}")
    if any(np.isnan(n) for n in a.shape):
        raise ValueError(f"{name} has unknown chunk sizes (shape {a.shape}): from_dask computes "
                         f"nothing; call {name}.compute_chunk_sizes() first")


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
        extras[name] = readonly(arr if owned else np.array(arr, copy=True))
    return extras



def _check_n_actions(n_actions) -> int:
    """``n_actions``, an integer ``>= 1``, as an int."""
    if isinstance(n_actions, bool) or not isinstance(n_actions, int | np.integer):
        raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
    if n_actions < 1:
        raise ValueError(f"n_actions must be >= 1, got {n_actions}")
    return int(n_actions)


def _check_feature_map(feature_map, n_actions) -> None:
    """A callable ``feature_map(states, actions) -> (n, d)`` and an integer ``n_actions >= 1``."""
    if not callable(feature_map):
        raise TypeError("feature_map must be callable: feature_map(states, actions) -> (n, d)")
    _check_n_actions(n_actions)
    _check_map_actions(feature_map, n_actions)


def _check_map_actions(feature_map, n_actions) -> None:
    """``n_actions`` agrees with a feature map that records its own (``cross_actions``)."""
    _st.check_map_actions(feature_map, n_actions)
