"""A nearest-neighbour model of a dataset of episodes, to simulate policies from data alone.

From an observation ``x`` at step ``t``, a policy's action ``a`` takes the transition
``(s_j, a, r_j, s'_j)`` of that action whose observation ``s_j`` is nearest to ``x``
(Euclidean distance after scaling every observation coordinate by its standard deviation
over the data; among ``n_neighbors`` nearest distinct observations, and among the
transitions that share an observation, one is drawn uniformly), and moves to

    x' = x + (s'_j - s_j)                      (the neighbour's change of state),

paying ``r_j``. A transition into an absorbing state ends the rollout with that state's
known value, re-shifted to step ``t`` for shifted rewards (see :mod:`r2pvi.episodes`).
A rollout whose observation is farther from every observation of the data than
``radius`` **halts** there with value 0, the lower end of the values' range ``[0, (H - h)
r_max]``: the data say nothing about what happens there, and the model is pessimistic
about it (as a pessimistic offline RL method is about uncovered features). The default
radius is the data's own largest nearest-neighbour distance. The steps are pooled (one
stationary environment).

On a finite MDP whose states are the observations and whose every state-action pair was
observed, ``x`` is always one of the data's observations, ``s_j = x``, nothing halts, and
the model is the empirical (maximum-likelihood) MDP of the data, whose values dynamic
programming gives. On continuous observations a policy that repeats the data's actions
replays the data's changes of state; one that deviates follows the changes of its own
actions and, when its states leave the data, is stopped with the worst value - so its own
state distribution, which no regression on the data's transitions sees, decides its
simulated return.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial import cKDTree

from .._validation import check_scalar
from .episodes import absorbing_values

__all__ = ["NeighbourModel"]


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


class NeighbourModel:
    """The nearest-neighbour model of a dataset of episodes (see the module docstring).

    Parameters
    ----------
    dataset : OfflineDataset
        Episodes (:meth:`~r2pvi.OfflineDataset.from_episodes` with a map crossed with the
        actions): it reads their observations (``dataset.states``,
        ``dataset.next_states``), taken actions, rewards and absorbing states.
    n_neighbors : int >= 1, default 1
        How many distinct nearest observations a transition is drawn from.
    radius : float > 0, optional
        A rollout farther than this from every observation of the data (in the scaled
        units) halts with value 0; None: the largest distance from an observation of the
        data to its nearest other one (:attr:`radius_`); ``numpy.inf``: never.

    Attributes
    ----------
    radius_ : float
        The halting radius in use.
    scale_ : ndarray (D,)
        The standard deviation of every observation coordinate (1 where it is 0).

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> from r2pvi.data import NeighbourModel
    >>> from r2pvi.features import StateAggregation, cross_actions
    >>> fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), 2)
    >>> ep = {"observations": [[0.0], [1.0], [1.0]], "actions": [1, 0],
    ...       "rewards": [0.0, 1.0], "terminations": [False, False],
    ...       "truncations": [False, True]}
    >>> model = NeighbourModel(OfflineDataset.from_episodes([ep], fmap, 2))
    >>> model.returns(lambda h, obs: np.where(obs[:, 0] > 0.5, 0, 1)).tolist()
    [1.0]
    """

    def __init__(self, dataset, n_neighbors: int = 1, radius=None):
        self.n_neighbors = _count(n_neighbors, "n_neighbors")
        phi = dataset._source.phi
        if dataset.states is None or not hasattr(phi, "actions"):
            raise ValueError(
                "a neighbour model needs a dataset of episodes: OfflineDataset.from_episodes("
                "episodes, cross_actions(map, A), A) keeps the observations, taken actions "
                "and absorbing states it reads")
        H, K, A = dataset.horizon, dataset.n_trajectories, dataset.n_actions
        self.horizon, self.n_actions = H, A
        actions = np.asarray(phi.actions)  # (H, K), -1 where no transition
        h_idx, k_idx = np.nonzero(actions >= 0)
        obs = np.asarray(dataset.states)
        self._obs_shape = obs.shape[2:]
        n = len(h_idx)
        self.states = obs[k_idx, h_idx].reshape(n, -1).astype(np.float64)
        self.changes = (np.asarray(dataset.next_states)[k_idx, h_idx].reshape(n, -1)
                        - self.states)
        self.actions = actions[h_idx, k_idx]
        self.rewards = np.asarray(dataset.rewards, dtype=np.float64)[k_idx, h_idx]
        self.offset = float(dataset._source.reward_offset or 0.0)
        enters, value = absorbing_values(dataset)
        self.terminal = enters[h_idx, k_idx]
        # an absorbing state's value at step h is base + (H - h - 1) * offset
        self.terminal_base = np.where(self.terminal,
                                      value[h_idx, k_idx] - (H - h_idx - 1) * self.offset, 0.0)
        self.initial_obs = obs[:, 0].reshape(K, -1).astype(np.float64)
        scale = self.states.std(axis=0)
        self.scale_ = np.where(scale > 0, scale, 1.0)
        x = self.states / self.scale_
        self._support = cKDTree(x)
        if radius is None:
            dist = self._support.query(x, k=2)[0][:, 1] if n > 1 else np.zeros(1)
            radius = float(dist.max())
        elif not (isinstance(radius, float | int) and radius == np.inf):
            radius = check_scalar(radius, "radius", low=0.0, low_inclusive=False)
        self.radius_ = float(radius)
        self._by_action = [self._index(np.flatnonzero(self.actions == a)) for a in range(A)]

    def _index(self, rows: np.ndarray):
        """``(tree over the distinct scaled observations, start, transitions)`` of one
        action: the transitions at distinct observation ``i`` are
        ``transitions[start[i]:start[i + 1]]`` (None when the action was never taken)."""
        if rows.size == 0:
            return None
        uniq, inverse = np.unique(self.states[rows] / self.scale_, axis=0,
                                  return_inverse=True)
        inverse = inverse.ravel()
        start = np.concatenate([[0], np.cumsum(np.bincount(inverse, minlength=len(uniq)))])
        return cKDTree(uniq), start, rows[np.argsort(inverse, kind="stable")]

    def draw(self, observations: np.ndarray, action: int, rng) -> np.ndarray:
        """Indices of the transitions drawn at ``observations (n, D)`` under ``action``."""
        index = self._by_action[action]
        if index is None:
            raise ValueError(
                f"the data never takes action {action}: a neighbour model cannot simulate it")
        tree, start, transitions = index
        n = len(observations)
        k = min(self.n_neighbors, tree.n)
        near = tree.query(observations / self.scale_, k=k)[1].reshape(n, k)
        counts = start[near + 1] - start[near]  # (n, k) transitions at each observation
        cum = np.cumsum(counts, axis=1)
        u = rng.random(n) * cum[:, -1]
        col = np.minimum((cum <= u[:, None]).sum(axis=1), k - 1)
        rows = np.arange(n)
        within = np.floor(u - cum[rows, col] + counts[rows, col]).astype(np.int64)
        within = np.clip(within, 0, counts[rows, col] - 1)
        return transitions[start[near[rows, col]] + within]

    def returns(self, policy, *, n_rollouts: int = 1, seed=0):
        """Simulated returns from each of the data's initial observations.

        Parameters
        ----------
        policy : callable
            ``policy(h, observations (n, ...)) -> actions (n,)``, called at every step with
            the observations of the rollouts still running (e.g. ``est.as_policy(map)``).
        n_rollouts : int >= 1, default 1
            Rollouts from every initial observation.
        seed : int, numpy.random.Generator or None, default 0

        Returns
        -------
        ndarray (K * n_rollouts,)
            Each rollout's sum of rewards over the horizon, plus the known value of the
            absorbing state it ends in (0 from where it halts), in the dataset's (shifted)
            reward units; rollouts of initial observation ``k`` are rows
            ``k * n_rollouts ... (k + 1) * n_rollouts - 1``.
        """
        n_rollouts = _count(n_rollouts, "n_rollouts")
        rng = np.random.default_rng(seed)
        obs = np.repeat(self.initial_obs, n_rollouts, axis=0)
        total = np.zeros(obs.shape[0])
        alive = np.arange(obs.shape[0])
        for t in range(self.horizon):
            near = self._support.query(obs[alive] / self.scale_)[0]
            alive = alive[near <= self.radius_]  # the others halt: value 0 from here
            if alive.size == 0:
                break
            act = self._actions(policy, t, obs[alive])
            j = np.empty(alive.size, dtype=np.int64)
            for a in np.unique(act):
                rows = act == a
                j[rows] = self.draw(obs[alive[rows]], int(a), rng)
            total[alive] += self.rewards[j]
            ends = self.terminal[j]
            total[alive[ends]] += (self.terminal_base[j[ends]]
                                   + (self.horizon - t - 1) * self.offset)
            alive, j = alive[~ends], j[~ends]
            obs[alive] += self.changes[j]
        return total

    def _actions(self, policy, t: int, obs: np.ndarray) -> np.ndarray:
        act = np.asarray(policy(t, obs.reshape((-1,) + self._obs_shape))).reshape(-1)
        if act.shape != (obs.shape[0],) or not np.issubdtype(act.dtype, np.integer) \
                or act.min() < 0 or act.max() >= self.n_actions:
            raise ValueError(
                f"policy(h, observations) must return {obs.shape[0]} integer actions in "
                f"[0, {self.n_actions}), got {act[:5]!r}")
        return act
