"""The simulated American put option (paper, Appendix A.2; Tamar et al. 2014, Ma et al. 2022)."""

from __future__ import annotations

import numpy as np

from .._validation import as_float_array, check_scalar
from ..data import OfflineDataset
from ._dataset import Trajectories, dataset_with_transitions
from ._sampling import as_generator, check_count
from .policies import is_estimator

__all__ = ["AmericanPutOption", "HOLD", "EXERCISE"]

HOLD, EXERCISE = 0, 1
_CHUNK = 32_768  # prices per estimator call


class AmericanPutOption:
    """An American put option on a binomial price process, with hat-function features.

    At every step ``h = 0..H-1`` the agent holds (action 0, reward 0; the price moves to
    ``up * s`` with probability ``p0``, else to ``down * s``) or exercises (action 1, reward
    ``max(0, strike - s)``, the episode ends). The initial price is uniform on ``s0_range``
    at every reset, or the fixed ``s0``.

    Holding has the d hat features ``phi_i(s) = max{0, 1 - |s - s_i| / Delta}`` with anchors
    ``s_i = first_anchor + (i - 1) Delta`` and ``Delta = anchor_span / d``: the paper's
    ``anchor_span = 60``, the authors' code ``anchor_span = 100``. Exercising is a terminal
    action whose value (its payoff) is known: its features are zero and datasets carry its
    payoff in ``next_values``, as in both public codebases. After exercise the state is NaN
    (zero features, known value 0).

    Parameters
    ----------
    p0 : float, default 0.5
        Probability that the price goes up.
    d : int, default 30
        Number of hat features.
    H : int, default 20
        Horizon.
    strike : float, default 100
    s0 : float, optional
        A fixed initial price; None draws it uniformly from ``s0_range`` at every reset.
    s0_range : (float, float), default (95, 105)
    first_anchor : float, default 80
    anchor_span : float, default 60
        ``Delta = anchor_span / d``; 60 in the paper, 100 in the authors' code.
    up, down : float, default 1.02, 0.98

    Examples
    --------
    >>> from r2pvi.envs import AmericanPutOption
    >>> env = AmericanPutOption()
    >>> env.spacing, env.anchors[:3].tolist()
    (2.0, [80.0, 82.0, 84.0])
    >>> float(env.features([81.0]).max()), env.payoff([81.0]).tolist()
    (0.5, [19.0])
    >>> ds = env.collect(50, seed=0)          # the behaviour policy always holds
    >>> ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions
    (50, 20, 30, 2)
    >>> AmericanPutOption(anchor_span=100).spacing    # the authors' code
    3.3333333333333335
    """

    gym_id = "r2pvi/AmericanPutOption-v0"
    n_actions = 2

    def __init__(self, p0=0.5, d=30, H=20, strike=100.0, *, s0=None, s0_range=(95.0, 105.0),
                 first_anchor=80.0, anchor_span=60.0, up=1.02, down=0.98):
        self.p0 = check_scalar(p0, "p0", low=0.0, high=1.0)
        self.d = check_scalar(d, "d", low=1, integer=True)
        self.H = check_scalar(H, "H", low=1, integer=True)
        self.strike = check_scalar(strike, "strike", low=0.0, low_inclusive=False)
        self.s0 = None if s0 is None else check_scalar(s0, "s0", low=0.0, low_inclusive=False)
        rng_ = as_float_array(s0_range, "s0_range", ndim=1)
        if rng_.shape != (2,) or not 0.0 < rng_[0] < rng_[1]:
            raise ValueError(f"s0_range must be (low, high) with 0 < low < high, got {s0_range}")
        self.s0_range = (float(rng_[0]), float(rng_[1]))
        self.first_anchor = check_scalar(first_anchor, "first_anchor")
        self.anchor_span = check_scalar(anchor_span, "anchor_span", low=0.0, low_inclusive=False)
        self.up = check_scalar(up, "up", low=0.0, low_inclusive=False)
        self.down = check_scalar(down, "down", low=0.0, low_inclusive=False)
        if not self.down < self.up:
            raise ValueError(f"down must be smaller than up, got down={down}, up={up}")
        self.spacing = self.anchor_span / self.d
        self.anchors = self.first_anchor + self.spacing * np.arange(self.d)

    # ------------------------------------------------------------------ the model
    @property
    def horizon(self) -> int:
        """H, the number of steps."""
        return self.H

    @property
    def n_features(self) -> int:
        """d, the feature dimension."""
        return self.d

    @property
    def r_max(self) -> float:
        """An upper bound on the reward: the strike."""
        return self.strike

    def features(self, prices) -> np.ndarray:
        """Hold features ``(n, d)`` of prices ``(n,)`` (zero for NaN, the ended state)."""
        s = np.asarray(prices, dtype=float).reshape(-1)
        return self._hat(s, np.empty((s.size, self.d)))

    def _hat(self, s: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``max{0, 1 - |s - s_i| / Delta}`` written into ``out (n, d)``; rows of NaN prices
        are zero.

        Only the anchors ``i = j - 1, ..., j + 2`` around ``j = floor((s - s_1) / Delta)`` are
        computed (with the formula's operations, so the values are the same bits): every
        other anchor is at least ``Delta`` (plus round-off margins) from ``s``, where the hat
        is 0.
        """
        out[...] = 0.0
        with np.errstate(invalid="ignore"):
            base = np.floor((s - self.first_anchor) / self.spacing)
        finite = np.isfinite(base)
        base[~finite] = -self.d - 4  # out of range for every candidate below
        for shift in (-1.0, 0.0, 1.0, 2.0):
            j = base + shift
            rows = np.flatnonzero((j >= 0) & (j < self.d))
            cols = j[rows].astype(np.intp)
            value = 1.0 - np.abs(s[rows] - self.anchors[cols]) / self.spacing
            out[rows, cols] = np.maximum(0.0, value)
        return out

    def phi_all(self, prices) -> np.ndarray:
        """Features of both actions ``(n, 2, d)``: hold features and zeros for exercise."""
        s = np.asarray(prices, dtype=float).reshape(-1)
        out = np.empty((s.size, 2, self.d))
        out[:, EXERCISE] = 0.0
        self._hat(s, out[:, HOLD])
        return out

    def payoff(self, prices) -> np.ndarray:
        """Exercise payoff ``max(0, strike - s)`` (0 for NaN, the ended state)."""
        s = np.asarray(prices, dtype=float).reshape(-1)
        return np.where(np.isnan(s), 0.0, np.maximum(0.0, self.strike - np.nan_to_num(s)))

    def known_values(self, prices) -> np.ndarray:
        """Known action values ``(n, 2)``: the payoff for exercise, NaN (learn) for hold;
        0 for both at the ended state (NaN price)."""
        s = np.asarray(prices, dtype=float).reshape(-1)
        out = np.empty((s.size, 2))
        out[:, HOLD] = np.where(np.isnan(s), 0.0, np.nan)
        out[:, EXERCISE] = self.payoff(s)
        return out

    @property
    def price_range(self) -> tuple[float, float]:
        """The smallest and largest reachable prices (initial range times down^H, up^H)."""
        lo, hi = (self.s0, self.s0) if self.s0 is not None else self.s0_range
        return lo * min(1.0, self.down**self.H), hi * max(1.0, self.up**self.H)

    def lattice_prices(self, s0, h: int) -> np.ndarray:
        """Prices ``s0 * up^u * down^(h-u)`` for ``u = 0..h`` at step ``h``."""
        u = np.arange(h + 1)
        return np.multiply.outer(np.asarray(s0, dtype=float), self.up**u * self.down ** (h - u))

    def perturbed(self, p0) -> AmericanPutOption:
        """The same option with another probability of a price rise."""
        kwargs = self.init_kwargs()
        kwargs["p0"] = p0
        return AmericanPutOption(**kwargs)

    # ------------------------------------------------------------------ acting
    def actions(self, policy, h: int, prices, rng=None) -> np.ndarray:
        """Actions ``(n,)`` of ``policy`` at step ``h`` for prices ``(n,)`` (all alive).

        ``policy`` is a fitted estimator (greedy on its Q-values, with the exercise payoff
        as the exercise action's known value; ties hold), a vectorized callable
        ``policy(h, prices) -> actions``, ``"hold"``, ``"exercise"`` or ``"uniform"``
        (needs ``rng``).
        """
        prices = np.asarray(prices, dtype=float).reshape(-1)
        n = prices.size
        if isinstance(policy, str):
            key = policy.lower()
            if key in ("hold", "behavior", "behaviour"):
                return np.zeros(n, dtype=np.int64)
            if key == "exercise":
                return np.ones(n, dtype=np.int64)
            if key == "uniform":
                if rng is None:
                    raise ValueError("the 'uniform' policy needs a random generator (seed)")
                return rng.integers(2, size=n)
            raise ValueError(
                f"policy must be 'hold', 'exercise', 'uniform', a fitted estimator or a callable "
                f"policy(h, prices) -> actions; got {policy!r}"
            )
        if is_estimator(policy):
            self._check_estimator(policy)
            out = np.empty(n, dtype=np.int64)
            for start in range(0, n, _CHUNK):  # bounded memory for long price grids
                part = prices[start : start + _CHUNK]
                out[start : start + _CHUNK] = self._greedy(policy, h, part)
            return out
        if callable(policy):
            out = np.asarray(policy(h, prices))
            if out.shape == () and n:
                out = np.full(n, out)
            if out.shape != (n,):
                raise ValueError(
                    f"policy(h, prices) must return one action per price, shape ({n},); got "
                    f"{out.shape} at h={h}"
                )
            if out.dtype == bool:
                out = out.astype(np.int64)
            if out.dtype.kind not in "iuf" or not np.isin(out, (0, 1)).all():
                raise ValueError(
                    "policy(h, prices) must return actions 0 (hold) or 1 (exercise)"
                )
            return out.astype(np.int64)
        raise TypeError(
            "a put-option policy is a fitted estimator, a vectorized callable "
            f"policy(h, prices) -> actions or 'hold'/'exercise'/'uniform'; got {policy!r}"
        )

    def _greedy(self, est, h: int, prices: np.ndarray) -> np.ndarray:
        """``argmax_a Q_h(s, a)`` of a fitted estimator, ties to hold: exercise exactly when
        its known value, the payoff, exceeds ``Q_h(s, hold)``.

        Only the hold action's Q is computed (exercise has zero features and a known value),
        half the work of ``est.act(phi_all, h, known_values)``, with the same decisions. An
        ended state (NaN price) has the known value 0 for both actions: it holds.
        """
        q_hold = est.q_values(self.features(prices)[:, None, :], h)[:, 0]
        with np.errstate(invalid="ignore"):  # NaN prices compare False: they hold
            exercise = np.maximum(0.0, self.strike - prices) > q_hold
        return exercise.astype(np.int64)

    def _check_estimator(self, est) -> None:
        horizon = getattr(est, "horizon_", None)
        if horizon is None:
            from .._compat import not_fitted_error

            raise not_fitted_error()(
                f"the {type(est).__name__} is not fitted: call fit(env.collect(...)) first"
            )
        if horizon != self.H or est.n_features_in_ != self.d:
            raise ValueError(
                f"the estimator was fitted with horizon {horizon} and {est.n_features_in_} "
                f"features, but the option has H = {self.H} and d = {self.d}"
            )

    def initial_prices(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` initial prices: the fixed ``s0`` or uniform draws from ``s0_range``."""
        if self.s0 is not None:
            return np.full(n, self.s0)
        return rng.uniform(*self.s0_range, size=n)

    # ------------------------------------------------------------------ sampling
    def simulate(self, n_trajectories: int, policy="hold", seed=None) -> Trajectories:
        """Sample trajectories, vectorized over trajectories.

        Returns ``Trajectories`` of ``(K, H)`` arrays: prices (NaN once exercised), actions
        (0 after exercise), rewards and next prices (NaN after exercise).
        """
        K = check_count(n_trajectories, "n_trajectories")
        rng = as_generator(seed)
        H = self.H
        states = np.full((K, H), np.nan)
        next_states = np.full((K, H), np.nan)
        actions = np.zeros((K, H), dtype=np.int64)
        rewards = np.zeros((K, H))
        s = self.initial_prices(K, rng)
        for h in range(H):
            alive = ~np.isnan(s)
            states[:, h] = s
            idx = np.flatnonzero(alive)
            a = self.actions(policy, h, s[idx], rng)
            actions[idx, h] = a
            ex = idx[a == EXERCISE]
            rewards[ex, h] = self.payoff(s[ex])
            moves = rng.random(K) < self.p0
            nxt = s * np.where(moves, self.up, self.down)
            nxt[ex] = np.nan
            next_states[:, h] = nxt
            s = nxt
        return Trajectories(states, actions, rewards, next_states)

    def collect(self, n_trajectories: int, policy="hold", seed=None) -> OfflineDataset:
        """An offline dataset collected by ``policy`` (the paper's behaviour: always hold).

        Holding steps carry the hat features; exercise steps have zero features and the
        payoff as reward; next-state exercise actions carry their payoff as a known value.
        Features are not on the simplex (by design), so no simplex warning is raised.
        """
        traj = self.simulate(n_trajectories, policy, seed)
        return self.make_dataset(*traj)

    def make_dataset(self, states, actions, rewards, next_states) -> OfflineDataset:
        """The :class:`~r2pvi.OfflineDataset` of observed prices ``(K, H)`` (NaN: ended)."""
        states = as_float_array(states, "states", ndim=2, allow_nan=True)
        K, H = states.shape
        if H != self.H:
            raise ValueError(f"states must have shape (K, H) with H = {self.H}, got {states.shape}")
        next_states = as_float_array(next_states, "next_states", ndim=2, allow_nan=True)
        rewards = as_float_array(rewards, "rewards", ndim=2)
        actions = np.asarray(actions)
        for name, arr in (("actions", actions), ("rewards", rewards),
                          ("next_states", next_states)):
            if arr.shape != (K, H):
                raise ValueError(f"{name} must have shape (K, H) = {(K, H)}, got {arr.shape}")
        if actions.dtype == bool or actions.dtype.kind not in "iu" or not np.isin(
            actions, (HOLD, EXERCISE)
        ).all():
            raise ValueError("actions must be integers 0 (hold) or 1 (exercise)")
        phi = self.phi_all(states.reshape(-1))
        phi = phi[np.arange(K * H), actions.reshape(-1)].reshape(K, H, self.d)
        next_phi = self.phi_all(next_states.reshape(-1)).reshape(K, H, 2, self.d)
        next_values = self.known_values(next_states.reshape(-1)).reshape(K, H, 2)
        return dataset_with_transitions(
            phi, rewards, next_phi, next_values, states, actions, next_states,
            check_simplex=False,
        )

    # ------------------------------------------------------------------ ecosystem
    def init_kwargs(self) -> dict:
        """JSON-friendly keyword arguments that rebuild this environment."""
        return {
            "p0": self.p0, "d": self.d, "H": self.H, "strike": self.strike, "s0": self.s0,
            "s0_range": list(self.s0_range), "first_anchor": self.first_anchor,
            "anchor_span": self.anchor_span, "up": self.up, "down": self.down,
        }

    def __repr__(self) -> str:
        start = f"s0={self.s0:g}" if self.s0 is not None else f"s0~U{self.s0_range}"
        return (
            f"AmericanPutOption(p0={self.p0:g}, d={self.d}, H={self.H}, strike={self.strike:g}, "
            f"{start}, spacing={self.spacing:g})"
        )
