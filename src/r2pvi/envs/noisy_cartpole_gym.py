"""The noisy CartPole protocol (:mod:`r2pvi.envs.noisy_cartpole`) as one Gymnasium
environment (extra ``gym``); registered as ``r2pvi/NoisyCartPole-v0`` by
:mod:`r2pvi.envs.gym`.

This module needs gymnasium; :class:`~r2pvi.envs.noisy_cartpole.NoisyCartPoleBatch` and
:func:`~r2pvi.envs.evaluate_cartpole_grid` do not.
"""

from __future__ import annotations

import numpy as np

from ._sampling import check_count
from .noisy_cartpole import (
    MAX_STEPS,
    NOMINAL,
    SIGMA,
    cartpole_step,
    check_cartpole_params,
    failed,
    initial_states,
)

try:  # the optional extra
    import gymnasium
    from gymnasium.envs.classic_control.cartpole import CartPoleEnv
except ImportError:  # pragma: no cover - exercised only without the extra
    gymnasium = None
    CartPoleEnv = object

__all__ = ["NoisyCartPoleEnv"]

_ACTION_NOISE = "action_noise"


def _require_gymnasium():
    if gymnasium is None:
        raise ImportError(
            "NoisyCartPoleEnv needs gymnasium: pip install 'r2pvi[gym]' (the NumPy "
            "NoisyCartPoleBatch and evaluate_cartpole_grid do not)"
        )


class NoisyCartPoleEnv(CartPoleEnv):
    """Gymnasium's CartPole with the RFQI protocol's noise, initial states and 200 steps.

    Parameters
    ----------
    sigma : float, default 0.1
        Dynamics noise (see :mod:`r2pvi.envs.noisy_cartpole`); 0 gives Gymnasium's dynamics.
    max_steps : int, default 200
        The episode is truncated after this many steps (no TimeLimit wrapper needed).
    render_mode : str, optional
    **params
        ``gravity, masscart, masspole, length, force_mag, tau`` (absolute values).

    Notes
    -----
    Parameters follow :class:`~r2pvi.envs.perturbations.PerturbedEnv`: read them with
    ``get_params()``, change them with ``set_params(**params)`` or at reset,
    ``reset(seed=..., options={"length": 1.0, "sigma": 0.0})``; they stay until changed.
    A reset with seed ``s`` draws from ``numpy.random.default_rng(s)``: 4 uniforms for the
    initial state, then 2 normals per step, so it runs the same episode as a row of
    :class:`~r2pvi.envs.noisy_cartpole.NoisyCartPoleBatch` with that episode seed.
    Observations are bounded only by float32's range (a noise draw near the singular
    denominator can throw the pole past any smaller bound in one step).
    Stepping after the episode ended raises ``RuntimeError``.

    Examples
    --------
    >>> from r2pvi.envs.noisy_cartpole_gym import NoisyCartPoleEnv
    >>> env = NoisyCartPoleEnv(length=1.0)
    >>> obs, info = env.reset(seed=0, options={"gravity": 19.6})
    >>> env.get_params()["gravity"], env.get_params()["sigma"]
    (19.6, 0.1)
    """

    def __init__(self, sigma: float = SIGMA, max_steps: int = MAX_STEPS,
                 render_mode: str | None = None, **params):
        _require_gymnasium()
        CartPoleEnv.__init__(self, render_mode=render_mode)
        self.max_steps = check_count(max_steps, "max_steps")
        high = np.full(4, np.finfo(np.float32).max, dtype=np.float32)
        self.observation_space = gymnasium.spaces.Box(-high, high, dtype=np.float32)
        self.sigma = SIGMA
        self._t = 0
        self._over = False
        self.set_params(sigma=sigma, **params)

    # ------------------------------------------------------------------ parameters
    def get_params(self) -> dict:
        """The current parameters: the six physical ones and ``sigma``."""
        out = {k: float(getattr(self, k)) for k in NOMINAL}
        out["sigma"] = float(self.sigma)
        return out

    def set_params(self, **params) -> None:
        """Change parameters (absolute values); ``total_mass`` and ``polemass_length``
        are recomputed."""
        if _ACTION_NOISE in params:
            raise ValueError("action_noise is not a parameter of NoisyCartPoleEnv: wrap it "
                             "in r2pvi.envs.perturbations.PerturbedEnv(env, action_noise=p)")
        for k, v in check_cartpole_params(params).items():
            setattr(self, k, v)
        self.total_mass = self.masspole + self.masscart
        self.polemass_length = self.masspole * self.length

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed=None, options=None):
        """Start an episode: theta ~ U(-0.2, 0.2), the other three components ~ U(-0.05,
        0.05); ``options`` set parameters first (as ``set_params``). Returns
        ``(observation, {})``."""
        if options:
            self.set_params(**options)
        gymnasium.Env.reset(self, seed=seed)
        self.state = initial_states(self.np_random.random(4))
        self.steps_beyond_terminated = None
        self._t = 0
        self._over = False
        if self.render_mode == "human":
            self.render()
        return self.state.astype(np.float32), {}

    def step(self, action):
        """Push the cart left (0) or right (1) for one Euler step with the protocol's noise.

        Returns ``(observation (4,) float32, reward 1.0, terminated, truncated, {})``: the
        reward is 1 on every step, the failing one included; ``terminated`` when
        ``|x| > 2.4`` or ``|theta| > 12`` degrees (or the state is no longer finite),
        ``truncated`` at ``max_steps``. Stepping an episode that is over raises
        ``RuntimeError``.
        """
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        if self._over:
            raise RuntimeError("the episode is over: call reset()")
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0 (push left) or 1 (push right), got {action!r}")
        noise = self.np_random.standard_normal((1, 2))
        params = {k: getattr(self, k) for k in NOMINAL}
        self.state = cartpole_step(self.state[None], np.array([int(action)]), sigma=self.sigma,
                                   noise=noise, **params)[0]
        self._t += 1
        terminated = bool(failed(self.state[None])[0])
        truncated = not terminated and self._t >= self.max_steps
        self._over = terminated or truncated
        if self.render_mode == "human":
            self.render()
        return self.state.astype(np.float32), 1.0, terminated, truncated, {}
