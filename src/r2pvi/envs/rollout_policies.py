"""Policies for rollouts in Gymnasium environments (:mod:`r2pvi.envs.collect`).

A policy is a callable ``policy(h, observations) -> actions`` acting on a batch: ``h`` is the
``(n,)`` integer array of the 0-based step of each row (sub-environments of a vector
environment are at different steps), ``observations`` the ``(n, ...)`` batch and the result
``(n,)`` integer actions. Stochastic policies are objects with ``sample(h, observations,
rngs)`` where ``rngs`` holds one ``numpy.random.Generator`` per row (each episode's own
stream): :class:`UniformPolicy`, :class:`EpsilonGreedy`. The string ``"uniform"`` is
:class:`UniformPolicy`. A fitted estimator's ``as_policy(feature_map)`` is a policy.
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = ["UniformPolicy", "EpsilonGreedy", "as_policy_function"]


class UniformPolicy:
    """Uniformly random actions among ``n_actions``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import UniformPolicy
    >>> rngs = [np.random.default_rng(s) for s in range(3)]
    >>> UniformPolicy(2).sample(np.zeros(3, int), np.zeros((3, 4)), rngs).shape
    (3,)
    """

    def __init__(self, n_actions: int):
        self.n_actions = _check_n_actions(n_actions)

    def sample(self, h, observations, rngs) -> np.ndarray:
        return np.array([rng.integers(self.n_actions) for rng in rngs], dtype=np.int64)

    def __repr__(self) -> str:
        return f"UniformPolicy({self.n_actions})"


class EpsilonGreedy:
    """With probability ``epsilon`` a uniformly random action, else ``policy``'s action.

    Parameters
    ----------
    policy : policy
        A deterministic callable ``policy(h, observations)`` or a stochastic policy.
    epsilon : float in [0, 1]
    n_actions : int

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import EpsilonGreedy
    >>> always_one = lambda h, obs: np.ones(len(obs), dtype=int)
    >>> rngs = [np.random.default_rng(s) for s in range(1000)]
    >>> acts = EpsilonGreedy(always_one, 0.3, 2).sample(np.zeros(1000, int), np.zeros(1000), rngs)
    >>> 0.1 < float((acts == 0).mean()) < 0.2          # 0.3 * 1/2 of the actions are 0
    True
    """

    def __init__(self, policy, epsilon: float, n_actions: int):
        if isinstance(epsilon, bool) or not isinstance(epsilon, numbers.Real) or not (
            0.0 <= float(epsilon) <= 1.0
        ):
            raise ValueError(f"epsilon must be a probability in [0, 1], got {epsilon!r}")
        self.policy = policy
        self.epsilon = float(epsilon)
        self.n_actions = _check_n_actions(n_actions)
        self._act = as_policy_function(policy, self.n_actions)

    def sample(self, h, observations, rngs) -> np.ndarray:
        actions = np.array(self._act(h, observations, rngs))  # checked by the rollout
        for i, rng in enumerate(rngs):
            if rng.random() < self.epsilon:
                actions[i] = rng.integers(self.n_actions)
        return actions

    def __repr__(self) -> str:
        return f"EpsilonGreedy({self.policy!r}, epsilon={self.epsilon}, n_actions={self.n_actions})"


def _check_n_actions(n_actions) -> int:
    if isinstance(n_actions, bool) or not isinstance(n_actions, numbers.Integral):
        raise TypeError(f"n_actions must be an integer, got {n_actions!r}")
    if n_actions < 1:
        raise ValueError(f"n_actions must be >= 1, got {n_actions}")
    return int(n_actions)


def as_policy_function(policy, n_actions: int | None):
    """``fn(h, observations, rngs) -> actions`` for any accepted policy form."""
    if isinstance(policy, str):
        if policy.lower() != "uniform":
            raise ValueError(
                f"policy must be 'uniform', a callable or a policy object, got {policy!r}"
            )
        if n_actions is None:
            raise ValueError("policy='uniform' needs a Discrete action space")
        policy = UniformPolicy(n_actions)
    if callable(getattr(policy, "sample", None)):
        return policy.sample
    if callable(policy):
        return lambda h, observations, rngs: policy(h, observations)
    raise TypeError(
        "policy must be a callable policy(h, observations) -> actions, an object with "
        f"sample(h, observations, rngs), or 'uniform'; got {type(policy).__name__}"
    )
