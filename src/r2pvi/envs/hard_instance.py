"""The hard instances of the paper's lower bound (Appendix "Construction of Hard Instances")."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np

from .._validation import as_float_array, check_scalar
from ..duals.fdivergence import FDivergence, get_divergence
from ._sampling import as_generator
from .finite import FiniteLinearMDP

__all__ = ["HardInstance"]

S1, S2 = 0, 1


class HardInstance(FiniteLinearMDP):
    """The d-rectangular linear RRMDP ``M_xi^lambda`` of the paper's lower-bound proof.

    Two states ``s1 = 0`` (good) and ``s2 = 1`` (absorbing fail state, reward 0), actions
    ``{0, 1}^d`` indexed in ``itertools.product([0, 1], repeat=d)`` order, features of
    dimension ``d + 2``:

    - ``phi(s1, a) = (a_1/d, ..., a_d/d, 1 - sum_i a_i/d, 0)``, ``phi(s2, a) = e_{d+2}``;
    - nominal factors, the same at every step: the first ``d + 1`` are
      ``(1 - epsilon) s1 + epsilon s2`` and the last is ``s2`` (from s1 the chain falls into
      s2 with probability epsilon whatever the action);
    - ``theta_h = delta ((xi_h + 1)/2, 1/2, 0)``, so ``r_h(s1, a) = delta (<xi_h, a> + d)/(2d)``
      and ``r_h(s2, a) = 0``; sampled rewards are ``N(r_h(s, a), 1)``;
    - initial distribution ``((d+1)/(d+2), 1/(d+2))``;
    - behaviour policy uniform on ``{e_1, ..., e_d, 0}``.

    The robust optimal action at s1 is ``a*_h = (1 + xi_h)/2`` (:attr:`optimal_actions`):
    the transitions do not depend on the action, so the best action maximizes the reward.

    Parameters
    ----------
    d : int
        Number of action coordinates (``2^d`` actions; keep it small).
    H : int
        Horizon.
    lam : float
        The regularizer ``lambda`` of the instance (kept as an attribute for evaluation).
    epsilon : float in (0, 1)
        The error injected into the nominal kernel.
    delta : float >= 0
        Reward scale separating the instances.
    xi : array_like (H, d) or (d,) of +-1
        The instance's sign vector (a ``(d,)`` vector is used at every step).
    divergence : str or FDivergence, default "tv"
        The divergence of the instance (kept as an attribute for evaluation).
    reward_noise : float, default 1.0
        Standard deviation of the Gaussian rewards.

    Examples
    --------
    >>> from r2pvi.envs import HardInstance
    >>> env = HardInstance(d=2, H=3, lam=1.0, epsilon=0.1, delta=0.5, xi=[1, -1])
    >>> env.n_actions, env.n_features, env.optimal_actions.tolist()   # a* = (1, 0): index 2
    (4, 4, [2, 2, 2])
    >>> env.features(0)[0, 2].tolist()                                # phi(s1, (1, 0))
    [0.5, 0.0, 0.5, 0.0]
    """

    gym_id = "r2pvi/HardInstance-v0"

    def __init__(self, d, H, lam, epsilon, delta, xi, divergence="tv", *, reward_noise=1.0):
        d = int(check_scalar(d, "d", low=1, integer=True))
        H = int(check_scalar(H, "H", low=1, integer=True))
        if d > 16:
            raise ValueError(f"d = {d} gives 2^d actions; use d <= 16")
        self.lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
        self.epsilon = check_scalar(epsilon, "epsilon", low=0.0, high=1.0)
        if not 0.0 < self.epsilon < 1.0:
            raise ValueError(f"epsilon must lie in (0, 1), got {epsilon}")
        self.delta = check_scalar(delta, "delta", low=0.0)
        if not isinstance(divergence, str | FDivergence | dict):
            raise TypeError(
                f"divergence must be 'tv', 'kl', 'chi2' or an FDivergence, got {divergence!r}"
            )
        resolved = get_divergence(divergence)  # validates names and parameter dicts
        self.divergence = divergence.lower() if isinstance(divergence, str) else resolved
        xi = as_float_array(xi, "xi")
        if xi.shape == (d,):
            xi = np.tile(xi, (H, 1))
        if xi.shape != (H, d):
            raise ValueError(f"xi must have shape (H, d) = {(H, d)} or (d,), got {xi.shape}")
        if not np.isin(xi, (-1.0, 1.0)).all():
            raise ValueError("xi must contain only -1 and +1")
        self.xi = xi
        self.d = d
        self.action_vectors = np.array(list(itertools.product([0, 1], repeat=d)), dtype=float)
        A = self.action_vectors.shape[0]
        phi = np.zeros((2, A, d + 2))
        phi[S1, :, :d] = self.action_vectors / d
        phi[S1, :, d] = 1.0 - self.action_vectors.sum(axis=1) / d
        phi[S2, :, d + 1] = 1.0
        theta = np.zeros((H, d + 2))
        theta[:, :d] = self.delta * (xi + 1.0) / 2.0
        theta[:, d] = self.delta / 2.0
        mu = np.zeros((H, d + 2, 2))
        mu[:, : d + 1, S1] = 1.0 - self.epsilon
        mu[:, : d + 1, S2] = self.epsilon
        mu[:, d + 1, S2] = 1.0
        initial = np.array([(d + 1.0) / (d + 2.0), 1.0 / (d + 2.0)])
        behavior = np.zeros((H, 2, A))
        behavior[:, :, self.behavior_actions] = 1.0 / (d + 1)
        super().__init__(phi, theta, mu, initial, fail_states=(S2,), reward_noise=reward_noise,
                         behavior_policy=behavior)

    @property
    def behavior_actions(self) -> np.ndarray:
        """Indices of the behaviour policy's actions ``{e_1, ..., e_d, 0}`` (``(d + 1,)``)."""
        d = self.d
        # In itertools.product order the bits are big-endian: e_i has index 2^(d-1-i).
        return np.array([1 << (d - 1 - i) for i in range(d)] + [0])

    @property
    def optimal_actions(self) -> np.ndarray:
        """The paper's optimal action indices ``a*_h = (1 + xi_h)/2``, ``(H,)``."""
        bits = ((1.0 + self.xi) / 2.0).astype(np.int64)
        return bits @ (1 << np.arange(self.d - 1, -1, -1))

    @classmethod
    def lower_bound_instance(cls, d, H, lam, n_trajectories, divergence="tv", xi=None,
                             seed=None) -> HardInstance:
        """The instance with the proof's parameters for a dataset of ``K = n_trajectories``.

        ``delta = d^{3/2} / sqrt(2K)`` and ``epsilon`` from eq. (definition of epsilon):
        ``1 - 2^{-1/H}`` for TV, ``min{1 - 2^{-1/H}, d^{3/2} / (64 lam sqrt(2K))}`` for KL and
        ``min{1 - 2^{-1/H}, d^{3/2} / (8 lam sqrt(2K))}`` for chi^2. ``xi=None`` draws the
        signs uniformly with ``seed``. Warns when ``K <= d^3 H^2 / (2 lam^2)`` (the lemma's
        condition).
        """
        K = int(check_scalar(n_trajectories, "n_trajectories", low=1, integer=True))
        lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
        name = divergence if isinstance(divergence, str) else get_divergence(divergence).name
        name = name.lower()
        base = 1.0 - 2.0 ** (-1.0 / H)
        scale = d**1.5 / math.sqrt(2.0 * K)
        if name == "tv":
            epsilon = base
        elif name == "kl":
            epsilon = min(base, scale / (64.0 * lam))
        elif name == "chi2":
            epsilon = min(base, scale / (8.0 * lam))
        else:
            raise ValueError(f"the lower bound is stated for 'tv', 'kl' and 'chi2', got {name!r}")
        if K <= d**3 * H**2 / (2.0 * lam**2):
            warnings.warn(
                f"K = {K} <= d^3 H^2 / (2 lam^2) = {d**3 * H**2 / (2 * lam**2):.4g}: the "
                "lower-bound lemma's condition does not hold",
                UserWarning,
                stacklevel=2,
            )
        if xi is None:
            xi = as_generator(seed).choice([-1.0, 1.0], size=(H, d))
        return cls(d, H, lam, epsilon, scale, xi, divergence)

    def init_kwargs(self) -> dict:
        div = self.divergence
        return {
            "d": self.d, "H": self.horizon, "lam": self.lam, "epsilon": self.epsilon,
            "delta": self.delta, "xi": self.xi.tolist(),
            "divergence": div if isinstance(div, str) else div.params,
            "reward_noise": self.reward_noise,
        }

    def __repr__(self) -> str:
        div = self.divergence if isinstance(self.divergence, str) else self.divergence.name
        return (
            f"HardInstance(d={self.d}, H={self.horizon}, lam={self.lam:g}, "
            f"epsilon={self.epsilon:g}, delta={self.delta:g}, divergence={div!r})"
        )
