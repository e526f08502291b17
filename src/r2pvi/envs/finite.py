"""Finite linear MDPs with explicit factors: ``P_h(s'|s,a) = sum_i phi_i(s,a) mu_{h,i}(s')``."""

from __future__ import annotations

import numbers

import numpy as np

from .._validation import as_float_array, as_index_array, check_scalar
from ..data import OfflineDataset
from ._dataset import Trajectories
from ._sampling import as_generator, check_count, sample_rows
from .policies import policy_table

__all__ = ["FiniteLinearMDP"]

_ATOL = 1e-9


class FiniteLinearMDP:
    """A finite-horizon linear MDP with known features, rewards and factor distributions.

    ``P_h(s'|s,a) = sum_i phi_i(s,a) mu_{h,i}(s')`` and ``r_h(s,a) = <phi(s,a), theta_h>``
    (the paper's Assumption 1, with 0-based steps ``h = 0..H-1``). States and actions are
    integer indices.

    Parameters
    ----------
    phi : array_like (S, A, d) or (H, S, A, d)
        Features, on the probability simplex (``phi_i >= 0``, ``sum_i phi_i = 1``); a 4-D
        array gives step-dependent features.
    theta : array_like (H, d)
        Reward parameters.
    mu : array_like (H, d, S)
        Factor distributions: ``mu[h, i]`` is ``mu_{h,i}``, a distribution over the S states.
    initial : array_like (S,) or int
        Initial-state distribution (an integer is a fixed start state).
    fail_states : sequence of int, optional
        Absorbing zero-reward states; their value (0) is passed to learners as a known value
        (``OfflineDataset.next_values``), as in the paper's experiments. Each must be
        absorbing with zero reward under every action and step.
    reward_noise : float, default 0.0
        Standard deviation of Gaussian noise added to sampled rewards (datasets, Monte Carlo,
        Gymnasium); exact evaluation uses the mean reward.
    behavior_policy : policy, optional
        The policy ``collect(policy="behavior")`` uses; uniform over actions by default. Any
        form accepted by :func:`r2pvi.envs.policies.policy_table` except ``"behavior"``.

    Examples
    --------
    A two-state chain: action 1 moves to the rewarding state 1 with probability 0.9.

    >>> import numpy as np
    >>> from r2pvi.envs import FiniteLinearMDP
    >>> phi = np.array([[[1.0, 0.0], [0.1, 0.9]],      # state 0: action 0 stays, action 1 moves
    ...                 [[0.0, 1.0], [0.0, 1.0]]])     # state 1: absorbing
    >>> mu = np.tile(np.eye(2), (2, 1, 1))              # factor i -> state i, H = 2
    >>> theta = np.array([[0.0, 1.0], [0.0, 1.0]])      # reward 1 in state 1
    >>> env = FiniteLinearMDP(phi, theta, mu, initial=0)
    >>> env.transition_matrix(0)[0, 1].tolist()         # P_0(. | s=0, a=1)
    [0.1, 0.9]
    >>> ds = env.collect(100, seed=0)
    >>> ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions
    (100, 2, 2, 2)
    """

    gym_id = "r2pvi/FiniteLinearMDP-v0"

    def __init__(self, phi, theta, mu, initial, *, fail_states=(), reward_noise=0.0,
                 behavior_policy=None):
        phi = as_float_array(phi, "phi")
        if phi.ndim not in (3, 4):
            raise ValueError(
                f"phi must have shape (S, A, d) or (H, S, A, d), got {phi.shape}"
            )
        theta = as_float_array(theta, "theta", ndim=2)
        mu = as_float_array(mu, "mu", ndim=3)
        H, d = theta.shape
        S, A = phi.shape[-3], phi.shape[-2]
        if H < 1 or S < 1 or A < 1 or d < 1:
            raise ValueError("H, S, A and d must all be >= 1")
        if phi.shape[-1] != d:
            raise ValueError(
                f"phi has d = {phi.shape[-1]} features but theta has shape (H, d) = {theta.shape}"
            )
        if phi.ndim == 4 and phi.shape[0] != H:
            raise ValueError(
                f"step-dependent phi must have shape (H, S, A, d) with H = {H} (from theta), "
                f"got {phi.shape}"
            )
        if mu.shape != (H, d, S):
            raise ValueError(
                f"mu must have shape (H, d, S) = {(H, d, S)} to match theta (H, d) and phi "
                f"(S = {S} states), got {mu.shape}"
            )
        _check_simplex_rows(phi, "phi", "phi(s, a) over the d features")
        _check_simplex_rows(mu, "mu", "mu[h, i] over the S states")
        self._phi = phi
        self._theta = theta
        self._mu = mu
        self._initial = _as_initial(initial, S)
        self._fail_states = _as_states(fail_states, S, "fail_states")
        self._reward_noise = check_scalar(reward_noise, "reward_noise", low=0.0)
        self._transitions = None
        self._rewards = None
        for s in self._fail_states:
            if not np.allclose(self.transitions[:, s, :, s], 1.0, atol=1e-9) or not np.allclose(
                self.reward_table[:, s, :], 0.0, atol=1e-12
            ):
                raise ValueError(
                    f"fail state {s} must be absorbing with zero reward at every step and "
                    "action (P_h(s|s,a) = 1, r_h(s,a) = 0); remove it from fail_states"
                )
        if isinstance(behavior_policy, str) and behavior_policy.lower() in (
            "behavior", "behaviour"
        ):
            raise ValueError("behavior_policy cannot be 'behavior' itself; give a policy")
        self._behavior = (
            np.full((H, S, A), 1.0 / A)
            if behavior_policy is None
            else policy_table(self, behavior_policy, "behavior_policy")
        )

    # ------------------------------------------------------------------ the model
    @property
    def horizon(self) -> int:
        """H, the number of steps."""
        return self._theta.shape[0]

    @property
    def n_states(self) -> int:
        """S, the number of states."""
        return self._mu.shape[2]

    @property
    def n_actions(self) -> int:
        """A, the number of actions."""
        return self._phi.shape[-2]

    @property
    def n_features(self) -> int:
        """d, the feature dimension."""
        return self._theta.shape[1]

    @property
    def phi(self) -> np.ndarray:
        """Features as given, ``(S, A, d)`` or ``(H, S, A, d)`` (read-only)."""
        return _readonly(self._phi)

    @property
    def theta(self) -> np.ndarray:
        """Reward parameters ``(H, d)`` (read-only)."""
        return _readonly(self._theta)

    @property
    def mu(self) -> np.ndarray:
        """Factor distributions ``(H, d, S)`` (read-only)."""
        return _readonly(self._mu)

    @property
    def initial(self) -> np.ndarray:
        """Initial-state distribution ``(S,)`` (read-only)."""
        return _readonly(self._initial)

    @property
    def fail_states(self) -> tuple[int, ...]:
        """Absorbing zero-reward states whose value is known (0)."""
        return self._fail_states

    @property
    def reward_noise(self) -> float:
        """Standard deviation of the Gaussian noise of sampled rewards."""
        return self._reward_noise

    @property
    def behavior_policy(self) -> np.ndarray:
        """The behaviour policy ``(H, S, A)`` used by ``collect(policy="behavior")``."""
        return _readonly(self._behavior)

    @property
    def r_max(self) -> float:
        """The largest mean reward ``max r_h(s, a)`` (at least 0)."""
        return float(max(self.reward_table.max(), 0.0))

    def features(self, h: int) -> np.ndarray:
        """Features of every state and action at step ``h``, ``(S, A, d)``."""
        return self._phi[h] if self._phi.ndim == 4 else self._phi

    @property
    def reward_table(self) -> np.ndarray:
        """Mean rewards ``r_h(s, a)``, ``(H, S, A)``."""
        if self._rewards is None:
            if self._phi.ndim == 4:
                r = np.einsum("hsad,hd->hsa", self._phi, self._theta)
            else:
                r = np.einsum("sad,hd->hsa", self._phi, self._theta)
            r.flags.writeable = False
            self._rewards = r
        return self._rewards

    @property
    def transitions(self) -> np.ndarray:
        """The transition kernel ``P[h, s, a, s']``, ``(H, S, A, S)``, from the factors."""
        if self._transitions is None:
            if self._phi.ndim == 4:
                p = np.einsum("hsad,hdt->hsat", self._phi, self._mu)
            else:
                p = np.einsum("sad,hdt->hsat", self._phi, self._mu)
            p.flags.writeable = False
            self._transitions = p
        return self._transitions

    def transition_matrix(self, h: int) -> np.ndarray:
        """``P_h(s'|s, a)`` at step ``h``, ``(S, A, S)``."""
        return self.transitions[h]

    @property
    def known_values(self) -> np.ndarray:
        """Known action values ``(S, A)``: 0 at fail states, NaN (learn) elsewhere."""
        out = np.full((self.n_states, self.n_actions), np.nan)
        out[list(self._fail_states)] = 0.0
        return out

    def with_factors(self, mu) -> FiniteLinearMDP:
        """The same features, rewards and start, with other factor distributions ``mu``.

        Perturbed test environments of the d-rectangular model are exactly this.
        """
        return FiniteLinearMDP(
            self._phi, self._theta, mu, self._initial, fail_states=self._fail_states,
            reward_noise=self._reward_noise, behavior_policy=self._behavior,
        )

    def state_distribution(self, policy="uniform") -> np.ndarray:
        """Exact distribution of ``s_h`` for ``h = 0..H`` under ``policy``, ``(H + 1, S)``."""
        pi = policy_table(self, policy)
        out = np.empty((self.horizon + 1, self.n_states))
        out[0] = self._initial
        for h in range(self.horizon):
            out[h + 1] = np.einsum("s,sa,sat->t", out[h], pi[h], self.transitions[h])
        return out

    # ------------------------------------------------------------------ sampling
    def simulate(self, n_trajectories: int, policy="uniform", seed=None) -> Trajectories:
        """Sample ``n_trajectories`` trajectories, vectorized over trajectories.

        Parameters
        ----------
        n_trajectories : int
        policy : policy, default "uniform"
            Any form accepted by :func:`~r2pvi.envs.policies.policy_table`.
        seed : None, int, SeedSequence or numpy.random.Generator

        Returns
        -------
        Trajectories
            ``states, actions, rewards, next_states``, each ``(K, H)``.
        """
        K = check_count(n_trajectories, "n_trajectories")
        pi = policy_table(self, policy)
        rng = as_generator(seed)
        H, S, A = self.horizon, self.n_states, self.n_actions
        # Filled step-major (contiguous rows per step), returned as (K, H) views.
        states = np.empty((H, K), dtype=np.int64)
        actions = np.empty((H, K), dtype=np.int64)
        next_states = np.empty((H, K), dtype=np.int64)
        rewards = np.empty((H, K))
        s = sample_rows(self._initial[None], np.zeros(K, dtype=np.intp), rng)
        for h in range(H):
            a = sample_rows(pi[h], s, rng)
            pair = s * A + a  # the (state, action) row of the step's kernel
            nxt = sample_rows(self.transitions[h].reshape(S * A, S), pair, rng)
            states[h], actions[h], next_states[h] = s, a, nxt
            rewards[h] = self.reward_table[h].reshape(-1)[pair]
            if self._reward_noise > 0.0:
                rewards[h] += self._reward_noise * rng.standard_normal(K)
            s = nxt
        return Trajectories(states.T, actions.T, rewards.T, next_states.T)

    def collect(self, n_trajectories: int, policy="uniform", seed=None) -> OfflineDataset:
        """An offline dataset of ``n_trajectories`` trajectories sampled by ``policy``.

        Features of the taken actions, the features of every action at the next state, the
        (noisy, if ``reward_noise > 0``) rewards, and 0 as the known value of every action
        at a fail state. The states, actions and next states are kept
        (``ds.states``, ``ds.actions``, ``ds.next_states``).
        """
        traj = self.simulate(n_trajectories, policy, seed)
        return self.make_dataset(*traj)

    def make_dataset(self, states, actions, rewards, next_states) -> OfflineDataset:
        """The :class:`~r2pvi.OfflineDataset` of observed integer transitions ``(K, H)``."""
        H, S, A = self.horizon, self.n_states, self.n_actions
        states = _as_index_array(states, S, "states")
        K = states.shape[0]
        if states.shape != (K, H):
            raise ValueError(f"states must have shape (K, H) with H = {H}, got {states.shape}")
        actions = _as_index_array(actions, A, "actions")
        next_states = _as_index_array(next_states, S, "next_states")
        for name, arr in (("actions", actions), ("next_states", next_states)):
            if arr.shape != (K, H):
                raise ValueError(f"{name} must have shape (K, H) = {(K, H)}, got {arr.shape}")
        rewards = as_float_array(rewards, "rewards", ndim=2)
        if rewards.shape != (K, H):
            raise ValueError(f"rewards must have shape (K, H) = {(K, H)}, got {rewards.shape}")
        steps = np.arange(H)
        next_steps = np.minimum(steps + 1, H - 1)  # the row of h = H-1 is never used
        # Gathered step-major, (H, K, d), and handed over as a (K, H, d) view: the dataset
        # stores it without another copy.
        pair = states.T * A + actions.T  # (H, K) rows of the (S * A, d) feature table
        if self._phi.ndim == 4:
            phi = self._phi.reshape(H, S * A, -1)[steps[:, None], pair]
            table = self._phi[next_steps]  # table[h]: the features of step h's next states
        else:
            phi = self._phi.reshape(S * A, -1).take(pair, axis=0)
            table = self._phi
        phi = phi.swapaxes(0, 1)
        # Next states are indices into the (S, A, d) feature table: nothing per sample is
        # stored, and V_{h+1} is computed once per state and gathered by index.
        return OfflineDataset.from_next_state_table(
            phi, rewards, next_states, table,
            self.known_values if self._fail_states else None,
            check_simplex=False,  # validated in the constructor
            states=states, actions=actions, reward_noise=self._reward_noise,
        )

    # ------------------------------------------------------------------ ecosystem
    def init_kwargs(self) -> dict:
        """JSON-friendly keyword arguments that rebuild this environment (Gymnasium specs)."""
        kwargs = {
            "phi": self._phi.tolist(),
            "theta": self._theta.tolist(),
            "mu": self._mu.tolist(),
            "initial": self._initial.tolist(),
        }
        if self._fail_states:
            kwargs["fail_states"] = list(self._fail_states)
        if self._reward_noise:
            kwargs["reward_noise"] = self._reward_noise
        return kwargs

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(H={self.horizon}, S={self.n_states}, A={self.n_actions}, "
            f"d={self.n_features})"
        )


# ---------------------------------------------------------------------- helpers
def _readonly(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v


def _check_simplex_rows(arr: np.ndarray, name: str, what: str) -> None:
    negative = arr < -_ATOL
    if negative.any():
        where = tuple(int(i) for i in np.argwhere(negative)[0])
        raise ValueError(
            f"{name} has a negative entry at index {where}: each {what} must be a probability "
            "distribution (non-negative, summing to 1)"
        )
    sums = arr.sum(axis=-1)
    bad = np.abs(sums - 1.0) > 1e-8
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{name}{list(where)} sums to {sums[where]:.10g}: each {what} must sum to 1 "
            "(the d-rectangular model needs simplex features and distributions as factors)"
        )


def _as_initial(initial, n_states: int) -> np.ndarray:
    if isinstance(initial, numbers.Integral) and not isinstance(initial, bool):
        if not 0 <= initial < n_states:
            raise ValueError(f"initial state must lie in [0, {n_states}), got {initial}")
        out = np.zeros(n_states)
        out[int(initial)] = 1.0
        return out
    out = as_float_array(initial, "initial", ndim=1)
    if out.shape != (n_states,):
        raise ValueError(
            f"initial must be a distribution over the S = {n_states} states (shape ({n_states},))"
            f" or a state index, got shape {out.shape}"
        )
    if (out < -_ATOL).any() or abs(out.sum() - 1.0) > 1e-8:
        raise ValueError(
            "initial must be a probability distribution (non-negative, summing to 1); got sum "
            f"{out.sum():.10g}"
        )
    return np.maximum(out, 0.0) / out.sum()


def _as_states(states, n_states: int, name: str) -> tuple[int, ...]:
    arr = np.atleast_1d(np.asarray(states))
    if arr.size == 0:
        return ()
    if arr.ndim != 1 or arr.dtype == bool or arr.dtype.kind not in "iu":
        raise TypeError(f"{name} must be a sequence of integer state indices, got {states!r}")
    if ((arr < 0) | (arr >= n_states)).any():
        raise ValueError(f"{name} must be state indices in [0, {n_states}), got {arr.tolist()}")
    return tuple(sorted({int(s) for s in arr}))


def _as_index_array(x, n: int, name: str) -> np.ndarray:
    arr = as_index_array(x, name, n)
    if arr.ndim != 2:
        raise ValueError(f"{name} must have shape (K, H), got {arr.shape}")
    return arr
