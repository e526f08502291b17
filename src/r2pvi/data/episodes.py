"""Episodes of any length -> :class:`~r2pvi.OfflineDataset` (the data layer for real tasks).

An episode holds Minari's ``EpisodeData`` fields: ``observations`` (T+1, ...), ``actions``
(T,), ``rewards`` (T,), ``terminations`` (T,) and ``truncations`` (T,). The dataset has
``K`` = the number of episodes and ``H`` = the given horizon or the longest episode:

- step ``h < T`` of an episode is the transition ``(o_h, a_h, r_h, o_{h+1})``, with features
  ``phi(o_h, a_h)`` and next-state features ``phi(o_{h+1}, a)`` for every action ``a``;
- a **terminated** episode continues in an absorbing state of known value 0: its last
  transition's next-state action values are known (``next_values = 0``); the steps after it
  carry no data;
- a **truncated** episode (or one cut at ``H``) ends with no terminal value: its last
  transition bootstraps from the learned ``V_T(o_T)`` (at ``T = H`` the value after the last
  step is 0 anyway);
- steps after an episode's end carry **no data**: zero features and reward, so they add
  nothing to a Gram matrix ``sum phi phi^T`` or to a regression ``sum phi y``. Their
  next-state row repeats a real next state of the same step (the first episode's that
  reaches it), so quantities taken over the sampled next values (TV's ``V_min = min_s V``,
  the TV ball's ``min_s [V]_alpha``) are those of the real transitions: a repeated value
  changes no minimum or maximum, and a zero row gives it no weight.

Rewards must lie in ``[0, r_max]`` (the estimators clip ``Q_h`` to ``[0, (H - h) r_max]``);
negative rewards (Acrobot, MountainCar pay -1 per step) are refused unless ``reward_offset``
shifts them: adding ``c`` to every reward, and ``(H - h - 1) c`` to the absorbing state's
value, adds ``(H - h) c`` to every policy's ``Q_h`` (and to its robust-regularized value:
the duals commute with constants), so the greedy policies are the same and values in the
original scale are ``Q_h - (H - h) c`` (exactly on the model; on ridge estimates up to the
shrinkage of ``gamma``, as ``E_hat[1]`` is slightly below 1). Set the estimator's ``r_max``
to at least the largest shifted reward. Returns measured in the environment are in the
original scale.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..features.maps import ActionCrossing, as_feature_map
from .build import _check_map_actions, check_simplex_features
from .build_crossed import crossed_episodes, episode_extras, padded_steps
from .build_sparse import sparse_episodes
from .storage.fields import _float_dtype

__all__ = ["Episode", "from_episodes", "episode_observations", "as_episode_list",
           "absorbing_values"]

_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


@dataclass
class Episode:
    """One episode with Minari's ``EpisodeData`` fields (``T`` steps).

    Attributes
    ----------
    observations : ndarray (T+1, ...)
    actions : ndarray (T,)
    rewards : ndarray (T,)
    terminations, truncations : ndarray of bool (T,)
    id : int, optional
    seed : int, optional
        The seed the environment was reset with (episodes collected by r2pvi).
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    id: int | None = None
    seed: int | None = None
    infos: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def total_reward(self) -> float:
        """The undiscounted return of the episode."""
        return float(np.sum(self.rewards))

    def __repr__(self) -> str:
        end = "terminated" if len(self) and self.terminations[-1] else "truncated"
        return f"Episode(id={self.id}, T={len(self)}, return={self.total_reward:g}, {end})"


def as_episode_list(episodes) -> list:
    """A list of episodes from a ``MinariDataset``, a single episode or an iterable."""
    if hasattr(episodes, "iterate_episodes"):
        return list(episodes.iterate_episodes())
    if isinstance(episodes, dict) or any(hasattr(episodes, f) for f in _FIELDS):
        return [episodes]
    if isinstance(episodes, str | bytes) or not hasattr(episodes, "__iter__"):
        raise TypeError(
            "episodes must be a minari.MinariDataset or an iterable of episodes (objects or "
            f"dicts with fields {', '.join(_FIELDS)}), got {type(episodes).__name__}"
        )
    return list(episodes)


def _field(ep, name: str, k: int):
    if isinstance(ep, dict):
        if name not in ep:
            raise ValueError(f"episode {k} has no {name!r} (needs {', '.join(_FIELDS)})")
        return ep[name]
    if not hasattr(ep, name):
        raise TypeError(
            f"episode {k} ({type(ep).__name__}) has no field {name!r}; episodes need Minari's "
            f"EpisodeData fields {', '.join(_FIELDS)}"
        )
    return getattr(ep, name)


def _check_episode(ep, k: int, n_actions: int):
    """The validated arrays of one episode: (obs (T+1, ...), actions, rewards, term, trunc)."""
    obs = np.asarray(_field(ep, "observations", k))
    if obs.dtype == object or obs.dtype.kind not in "biuf":
        raise TypeError(
            f"episode {k}: observations must be a numeric array (T+1, ...), got dtype "
            f"{obs.dtype} (flatten dict observations with gymnasium.spaces.flatten)"
        )
    acts = np.asarray(_field(ep, "actions", k))
    if acts.ndim == 2 and acts.shape[1] == 1:
        acts = acts[:, 0]
    rew = np.asarray(_field(ep, "rewards", k), dtype=float).reshape(-1)
    T = rew.shape[0]
    if acts.shape != (T,):
        raise ValueError(
            f"episode {k}: actions must have shape (T,) = ({T},) like rewards, got {acts.shape}"
        )
    if acts.dtype == bool or acts.dtype.kind not in "iuf" or (
        acts.dtype.kind == "f" and not np.all(acts == np.round(acts))
    ):
        raise TypeError(f"episode {k}: actions must be integer indices (discrete actions)")
    acts = acts.astype(np.int64)
    if T and ((acts < 0) | (acts >= n_actions)).any():
        raise ValueError(
            f"episode {k}: actions must lie in [0, n_actions={n_actions}), got "
            f"{acts.min()}..{acts.max()}"
        )
    if obs.ndim == 0 or obs.shape[0] != T + 1:
        raise ValueError(
            f"episode {k}: observations must have T+1 = {T + 1} rows (Minari stores the last "
            f"observation too), got shape {obs.shape}"
        )
    if not np.isfinite(rew).all():
        raise ValueError(f"episode {k}: rewards contain NaN or infinite entries")
    flags = []
    for name in ("terminations", "truncations"):
        f = np.asarray(_field(ep, name, k)).reshape(-1)
        if f.shape != (T,):
            raise ValueError(f"episode {k}: {name} must have shape ({T},), got {f.shape}")
        flags.append(f.astype(bool))
    term, trunc = flags
    if T and (term[:-1].any() or trunc[:-1].any()):
        raise ValueError(
            f"episode {k}: terminations/truncations are set before the last step; split it "
            "into separate episodes"
        )
    return obs, acts, rew, term, trunc


def from_episodes(cls, episodes, feature_map, n_actions: int, horizon: int | None = None, *,
                  reward_offset=None, check_simplex: bool = True, dtype=None):
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
    dtype : {None, "float32", "float64"}, default None
        Storage type of the features (None: float64). Fits accumulate in float64 either
        way; float32 halves the memory of large datasets.

    With a feature map crossed with the actions (:func:`~r2pvi.features.cross_actions`,
    or a fitted observation transformer) whose observation map gives dense rows, the
    dataset stores the observation features ``psi`` once per observation and the actions
    by index (:mod:`r2pvi.data.storage.crossed`): ``m`` numbers per transition instead of
    ``(1 + A) A m``, and pooled fits (``time_homogeneous=True``) that read ``psi`` twice a
    step. The numbers are those of the dense rows.

    The dataset is :attr:`~r2pvi.OfflineDataset.stationary`: the estimators' default
    ``time_homogeneous="auto"`` pools its steps.

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
    _check_map_actions(feature_map, n_actions)
    if isinstance(n_actions, bool) or not isinstance(n_actions, numbers.Integral):
        raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
    if n_actions < 1:
        raise ValueError(f"n_actions must be >= 1, got {n_actions}")
    A = int(n_actions)
    fmap = as_feature_map(feature_map, A)
    eps = [_check_episode(ep, k, A) for k, ep in enumerate(as_episode_list(episodes))]
    if not eps:
        raise ValueError("episodes is empty: a dataset needs at least one episode")
    longest = max(len(e[2]) for e in eps)
    if horizon is None:
        H = longest
        if H == 0:
            raise ValueError("every episode has 0 steps: nothing to learn from")
    else:
        if isinstance(horizon, bool) or not isinstance(horizon, numbers.Integral):
            raise TypeError(f"horizon must be a positive integer or None, got {horizon!r}")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        H = int(horizon)
    obs_shape = eps[0][0].shape[1:]
    for k, e in enumerate(eps):
        if e[0].shape[1:] != obs_shape:
            raise ValueError(
                f"episode {k}: observations have shape {e[0].shape[1:]} per step, episode 0 "
                f"has {obs_shape}"
            )
    K = len(eps)
    # Flatten the real steps (cut at H) of every episode.
    lengths = np.array([min(len(e[2]), H) for e in eps])
    k_idx = np.repeat(np.arange(K), lengths)
    h_idx = np.concatenate([np.arange(n) for n in lengths]) if lengths.sum() else np.zeros(0, int)
    cur = np.concatenate([e[0][:n] for e, n in zip(eps, lengths, strict=True)])
    nxt = np.concatenate([e[0][1:n + 1] for e, n in zip(eps, lengths, strict=True)])
    acts = np.concatenate([e[1][:n] for e, n in zip(eps, lengths, strict=True)])
    rews = np.concatenate([e[2][:n] for e, n in zip(eps, lengths, strict=True)])
    # The last transition of an episode that terminated within the horizon: absorbing next.
    ends = np.cumsum(lengths) - 1
    absorbing = np.zeros(len(rews), dtype=bool)
    for k, e in enumerate(eps):
        T = len(e[2])
        if T and T <= H and e[3][-1]:
            absorbing[ends[k]] = True

    offset = _reward_offset(reward_offset, rews)
    N = len(rews)
    if dtype is not None:
        dtype = _float_dtype(dtype)
    if isinstance(fmap, ActionCrossing):  # psi once per observation, unless sparse rows
        ds = crossed_episodes(cls, fmap, eps, lengths, h_idx, k_idx, cur, nxt, acts,
                              rews + offset, absorbing, offset, K, H, A, check_simplex, dtype)
        if ds is not None:
            return ds
    phi_flat = fmap(cur, acts)
    if sp.issparse(phi_flat):  # tile coding, aggregation: sparse rows all the way
        ds = sparse_episodes(cls, phi_flat, fmap, nxt, rews + offset, h_idx, k_idx, absorbing,
                             offset, K, H, A, check_simplex)
        ds._source.stationary, ds._source.reward_offset = True, offset
        return ds
    phi_flat = _dense(phi_flat, N, "feature_map(observations, actions)")
    d = phi_flat.shape[1]
    ok = not check_simplex or check_simplex_features(  # real rows only: padding is zero
        phi_flat, "feature_map(observations, actions)")
    # Step-major arrays (the storage's layout), handed over as (K, H, ...) views.
    phi = np.zeros((H, K, d))
    phi[h_idx, k_idx] = phi_flat
    del phi_flat
    next_phi = np.zeros((H, K, A, d))
    for a in range(A):  # one action at a time: no (N, A, d) intermediate
        out = _dense(fmap(nxt, np.full(N, a)), N, "feature_map(next observations, actions)", d)
        if ok and check_simplex:
            ok = check_simplex_features(out[~absorbing], "feature_map(next observations, a)")
        next_phi[h_idx, k_idx, a] = out
    rewards = np.zeros((H, K))
    rewards[h_idx, k_idx] = rews + offset
    next_values = np.full((H, K, A), np.nan)
    # Absorbing state after termination: value (H - h - 1) * offset (0 without an offset).
    next_values[h_idx[absorbing], k_idx[absorbing]] = (H - h_idx[absorbing] - 1)[:, None] * offset
    extras = episode_extras(cur, nxt, h_idx, k_idx, acts, K, H)
    real = np.zeros((H, K), dtype=bool)
    real[h_idx, k_idx] = True
    for h, src, pad in padded_steps(real):  # repeat a real next state (module docstring)
        next_phi[h, pad] = next_phi[h, src]
        next_values[h, pad] = next_values[h, src]
    ds = cls.from_features(
        phi.transpose(1, 0, 2), rewards.T, next_phi.transpose(1, 0, 2, 3),
        next_values.transpose(1, 0, 2), check_simplex=False, dtype=dtype,
        **extras,
    )
    # draws of one environment: the pooled form by default
    ds._source.stationary, ds._source.reward_offset = True, offset
    return ds


def _reward_offset(reward_offset, rewards: np.ndarray) -> float:
    low = float(rewards.min()) if rewards.size else 0.0
    if reward_offset is None:
        if low < 0:
            raise ValueError(
                f"rewards go down to {low:g} < 0, but the estimators clip Q_h to "
                "[0, (H - h) r_max], so every Q would be 0. Pass reward_offset='auto' (adds "
                f"{-low:g} to every reward and the matching (H - h - 1) * {-low:g} to absorbing "
                "states: the same greedy policy, values higher by (H - h) * offset) or a number "
                ">= the largest negative part, and set the estimator's r_max to at least the "
                "largest shifted reward"
            )
        return 0.0
    if isinstance(reward_offset, str):
        if reward_offset.lower() != "auto":  # case-insensitive, as every string option
            raise ValueError(
                f"reward_offset must be None, 'auto' or a number, got {reward_offset!r}"
            )
        return max(0.0, -low)
    if isinstance(reward_offset, bool) or not isinstance(reward_offset, numbers.Real):
        raise TypeError(f"reward_offset must be None, 'auto' or a number, got {reward_offset!r}")
    c = float(reward_offset)
    if not np.isfinite(c):
        raise ValueError(f"reward_offset must be finite, got {reward_offset!r}")
    if low + c < 0:
        raise ValueError(
            f"reward_offset={c:g} leaves rewards down to {low + c:g} < 0; use at least {-low:g} "
            "(or 'auto')"
        )
    return c


def _dense(x, n: int, what: str, d: int | None = None) -> np.ndarray:
    if hasattr(x, "toarray"):  # scipy.sparse rows: stored dense in the dataset for now
        x = x.toarray()
    arr = np.asarray(x, dtype=float)
    if arr.ndim != 2 or arr.shape[0] != n or (d is not None and arr.shape[1] != d):
        want = f"({n}, {'d' if d is None else d})"
        raise ValueError(f"{what} must return {want}, got shape {arr.shape}")
    return arr


def episode_observations(episodes) -> np.ndarray:
    """Every observation of every episode stacked, ``(sum (T+1), ...)``: what feature maps fit.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.episodes import episode_observations
    >>> ep = {"observations": np.zeros((3, 2)), "actions": [0, 1], "rewards": [1.0, 1.0],
    ...       "terminations": [False, True], "truncations": [False, False]}
    >>> episode_observations([ep, ep]).shape
    (6, 2)
    """
    eps = as_episode_list(episodes)
    if not eps:
        raise ValueError("episodes is empty")
    return np.concatenate([np.asarray(_field(ep, "observations", k)) for k, ep in enumerate(eps)])


def absorbing_values(dataset) -> tuple[np.ndarray, np.ndarray]:
    """``(enters (H, K), value (H, K))`` of a dataset of episodes: whether step ``h``'s
    transition of trajectory ``k`` (a row with a taken action) enters an absorbing state,
    and that state's known value (``(H - h - 1) c`` for rewards shifted by ``c``; 0
    elsewhere). The rows after an episode's end repeat another episode's next state and its
    known values: they are not transitions."""
    actions = np.asarray(dataset._source.phi.actions)  # (H, K), -1 after the end
    if not dataset.has_known_values:
        return np.zeros(actions.shape, dtype=bool), np.zeros(actions.shape)
    known = np.stack([dataset._source.next.known(h) for h in range(dataset.horizon)])
    enters = ~np.isnan(known).all(axis=2) & (actions >= 0)
    value = np.max(np.where(np.isnan(known), -np.inf, known), axis=2)
    return enters, np.where(enters, value, 0.0)
