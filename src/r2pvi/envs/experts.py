"""Hand-built expert controllers for classic-control tasks (no neural network, no training).

Robust offline RL benchmarks (RFQI, Panaganti et al. 2022) collect their data with an
epsilon-greedy expert in the nominal environment. These experts are policies in the sense of
:mod:`r2pvi.envs.rollout_policies`: ``policy(h, observations) -> actions`` on a batch.

- :class:`CartPoleLQR`: a linear state-feedback controller for CartPole, its gain the
  infinite-horizon discrete LQR gain of the dynamics linearized at the upright position
  (Euler step of Gymnasium's equations, computed with ``scipy.linalg.solve_discrete_are``),
  applied bang-bang: push right when the LQR force is positive;
- :class:`MountainCarEnergy`: push in the direction of the car's velocity (energy pumping).

Examples
--------
>>> import gymnasium as gym
>>> from r2pvi.envs.experts import CartPoleLQR
>>> from r2pvi.evaluation import evaluate_policy
>>> expert = CartPoleLQR()
>>> expert.gain_.round(2).tolist()                   # u = -gain @ (x, x_dot, theta, theta_dot)
[-0.79, -1.38, -9.03, -2.39]
>>> evaluate_policy(gym.make("CartPole-v1"), expert, 10, seed=0, max_steps=200, n_envs=10)
(200.0, 0.0)
"""

from __future__ import annotations

import numpy as np

__all__ = ["CartPoleLQR", "MountainCarEnergy", "cartpole_linearization"]

CARTPOLE_NOMINAL = {"gravity": 9.8, "masscart": 1.0, "masspole": 0.1, "length": 0.5,
                    "force_mag": 10.0, "tau": 0.02}


def cartpole_linearization(gravity=9.8, masscart=1.0, masspole=0.1, length=0.5,
                           force_mag=10.0, tau=0.02):
    """``(A, B)`` of CartPole linearized at the upright rest state, one Euler step of ``tau``.

    State ``(x, x_dot, theta, theta_dot)``, control ``u`` in units of ``force_mag`` (the
    force is ``u * force_mag``). At ``theta = theta_dot = 0`` Gymnasium's equations read
    ``theta_acc = (g theta - F / M) / (l (4/3 - m_p / M))`` and
    ``x_acc = F / M - m_p l theta_acc / M`` with ``M = m_c + m_p`` and ``l`` the half length.

    Examples
    --------
    >>> from r2pvi.envs.experts import cartpole_linearization
    >>> A, B = cartpole_linearization()
    >>> A.shape, B.shape
    ((4, 4), (4, 1))
    """
    M = masscart + masspole
    den = length * (4.0 / 3.0 - masspole / M)
    th_theta, th_force = gravity / den, -1.0 / (M * den)
    x_theta = -masspole * length * th_theta / M
    x_force = 1.0 / M - masspole * length * th_force / M
    Ac = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, x_theta, 0.0],
                   [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, th_theta, 0.0]])
    Bc = np.array([[0.0], [x_force], [0.0], [th_force]]) * force_mag
    return np.eye(4) + tau * Ac, tau * Bc


def _batch(observations, width: int) -> np.ndarray:
    obs = np.asarray(observations, dtype=float)
    if obs.ndim == 1:
        obs = obs[None]
    if obs.ndim != 2 or obs.shape[1] != width:
        raise ValueError(f"observations must have shape (n, {width}), got {obs.shape}")
    return obs


class CartPoleLQR:
    """Bang-bang LQR controller for CartPole: action 1 (push right) iff ``-gain @ s > 0``.

    Parameters
    ----------
    state_cost : sequence of 4 floats, default (1, 1, 10, 1)
        Diagonal of the LQR state cost ``Q`` on ``(x, x_dot, theta, theta_dot)``.
    action_cost : float, default 1
        The LQR control cost ``R`` (control in units of ``force_mag``).
    **params
        Physical parameters the gain is designed for (Gymnasium's nominal CartPole by
        default): ``gravity, masscart, masspole, length, force_mag, tau``.

    Attributes
    ----------
    gain_ : ndarray (4,)
        The LQR gain ``K``: the linear control is ``u = -K s``.

    Notes
    -----
    The gain is designed once, for the nominal parameters; evaluated in a perturbed
    environment the controller is *not* redesigned (it is the data-collecting expert).
    """

    def __init__(self, state_cost=(1.0, 1.0, 10.0, 1.0), action_cost=1.0, **params):
        from scipy.linalg import solve_discrete_are

        unknown = sorted(set(params) - set(CARTPOLE_NOMINAL))
        if unknown:
            raise ValueError(f"unknown CartPole parameter(s) {unknown}; valid: "
                             f"{sorted(CARTPOLE_NOMINAL)}")
        q = np.asarray(state_cost, dtype=float)
        if q.shape != (4,) or not np.isfinite(q).all() or (q < 0).any():
            raise ValueError(f"state_cost must be 4 non-negative numbers, got {state_cost!r}")
        r = float(action_cost)
        if not np.isfinite(r) or r <= 0:
            raise ValueError(f"action_cost must be a positive number, got {action_cost!r}")
        self.state_cost = tuple(q.tolist())
        self.action_cost = r
        self.params = {**CARTPOLE_NOMINAL, **{k: float(v) for k, v in params.items()}}
        A, B = cartpole_linearization(**self.params)
        P = solve_discrete_are(A, B, np.diag(q), np.array([[r]]))
        self.gain_ = np.linalg.solve(r + B.T @ P @ B, B.T @ P @ A)[0]

    def __call__(self, h, observations) -> np.ndarray:
        """Actions ``(n,)``: 1 where the LQR force ``-gain @ s`` is positive, else 0."""
        obs = _batch(observations, 4)
        return (obs @ self.gain_ < 0.0).astype(np.int64)

    def __repr__(self) -> str:
        return f"CartPoleLQR(gain={np.round(self.gain_, 3).tolist()})"


class MountainCarEnergy:
    """MountainCar expert: accelerate in the direction of the velocity (action 2 if
    ``velocity >= 0``, else 0), which pumps energy into the oscillation until the car
    reaches the flag.

    Examples
    --------
    >>> import gymnasium as gym
    >>> from r2pvi.envs.experts import MountainCarEnergy
    >>> from r2pvi.evaluation import evaluate_policy
    >>> mean, se = evaluate_policy(gym.make("MountainCar-v0"), MountainCarEnergy(), 10, seed=0,
    ...                            max_steps=200, n_envs=10)
    >>> -200 < mean < -80
    True
    """

    def __call__(self, h, observations) -> np.ndarray:
        """Actions ``(n,)`` in ``{0, 2}``."""
        obs = _batch(observations, 2)
        return np.where(obs[:, 1] >= 0.0, 2, 0).astype(np.int64)

    def __repr__(self) -> str:
        return "MountainCarEnergy()"
