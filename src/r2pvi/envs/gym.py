"""Gymnasium adapters for every r2pvi environment (optional extra ``gym``).

Importing this module registers the ids

- ``r2pvi/FiniteLinearMDP-v0`` (kwargs ``phi, theta, mu, initial``, ...),
- ``r2pvi/SimulatedLinearMDP-v0`` (kwargs ``delta, xi_norm``, optional ``q``),
- ``r2pvi/HardInstance-v0`` (kwargs ``d, H, lam, epsilon, delta, xi``, ...),
- ``r2pvi/AmericanPutOption-v0`` (kwargs ``p0, d, H, strike``, ...),
- ``r2pvi/NoisyCartPole-v0`` (kwargs ``sigma, max_steps`` and CartPole's parameters: the
  RFQI protocol, :mod:`r2pvi.envs.noisy_cartpole_gym`),

so ``gymnasium.make("r2pvi/SimulatedLinearMDP-v0")`` works after ``import r2pvi.envs.gym``
(or in one line: ``gymnasium.make("r2pvi.envs.gym:r2pvi/SimulatedLinearMDP-v0")``).
``as_gymnasium_env(env)`` wraps an existing r2pvi environment (the adapters import the
environments; the environments never import the adapters).

Observations are state indices (``Discrete(S)``) for the finite models and the price
(``Box(low, high, (1,))`` over the reachable prices) for the put option; actions are
``Discrete(A)``. Episodes last H steps and end with ``truncated=True`` (the finite
horizon); exercising the put option ends the episode with ``terminated=True``. ``info``
holds the next decision's 0-based ``step``, the features ``phi`` of every action at the
current state ``(A, d)``, a boolean mask
``known`` ``(A,)`` of the actions whose value is known (fail states, exercise) and those
``known_values`` (0 where not known; NaN is avoided so that Gymnasium's determinism checks
apply), so that a fitted estimator can act with :func:`greedy_action`::

    a = greedy_action(est, info)

Sampled rewards are those of the datasets (``N(r, 1)`` for the hard instance). The r2pvi
model is ``env.unwrapped.model``.

This module imports without Gymnasium installed; creating an environment then raises an
ImportError that names the extra.
"""

from __future__ import annotations

import json

import numpy as np

from ._sampling import sample_categorical
from .finite import FiniteLinearMDP
from .hard_instance import HardInstance
from .put_option import EXERCISE, AmericanPutOption
from .simulated import SimulatedLinearMDP

try:  # the optional extra
    import gymnasium
    from gymnasium import spaces
except ImportError:  # pragma: no cover - exercised only without the extra
    gymnasium = None
    spaces = None

__all__ = [
    "FiniteLinearMDPEnv",
    "AmericanPutOptionEnv",
    "as_gymnasium_env",
    "greedy_action",
    "register_envs",
    "ENV_IDS",
]

_ENTRY_POINTS = {
    FiniteLinearMDP.gym_id: "make_finite_linear_mdp",
    SimulatedLinearMDP.gym_id: "make_simulated_linear_mdp",
    HardInstance.gym_id: "make_hard_instance",
    AmericanPutOption.gym_id: "make_american_put_option",
}
NOISY_CARTPOLE_ID = "r2pvi/NoisyCartPole-v0"
#: The registered environment ids.
ENV_IDS = (*_ENTRY_POINTS, NOISY_CARTPOLE_ID)


def _require_gymnasium():
    if gymnasium is None:
        raise ImportError(
            "the Gymnasium adapters need gymnasium: pip install 'r2pvi[gym]' "
            "(or pip install gymnasium)"
        )


_Base = gymnasium.Env if gymnasium is not None else object


class FiniteLinearMDPEnv(_Base):
    """A :class:`~r2pvi.envs.FiniteLinearMDP` (or subclass) as a Gymnasium environment.

    Parameters
    ----------
    model : FiniteLinearMDP

    Examples
    --------
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> env = as_gymnasium_env(SimulatedLinearMDP())           # doctest: +SKIP
    >>> obs, info = env.reset(seed=0)                          # doctest: +SKIP
    >>> obs, info["step"], info["phi"].shape                   # doctest: +SKIP
    (0, 0, (16, 4))
    """

    metadata = {"render_modes": []}

    def __init__(self, model: FiniteLinearMDP):
        _require_gymnasium()
        if not isinstance(model, FiniteLinearMDP):
            raise TypeError(f"model must be a FiniteLinearMDP, got {type(model).__name__}")
        self.model = model
        self.observation_space = spaces.Discrete(model.n_states)
        self.action_space = spaces.Discrete(model.n_actions)
        self._known = model.known_values
        self._h = None
        self._state = None

    def _info(self):
        h = min(self._h, self.model.horizon - 1)
        return {
            "step": self._h,
            "phi": self.model.features(h)[self._state].copy(),
            "known": ~np.isnan(self._known[self._state]),
            "known_values": np.nan_to_num(self._known[self._state]),
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._h = 0
        self._state = int(sample_categorical(self.model.initial[None], self.np_random)[0])
        return self._state, self._info()

    def step(self, action):
        if self._h is None:
            raise RuntimeError("call reset() before step()")
        if self._h >= self.model.horizon:
            raise RuntimeError("the episode is over (H steps taken): call reset()")
        a = _as_action(action, self.model.n_actions)
        h, s = self._h, self._state
        reward = float(self.model.reward_table[h, s, a])
        if self.model.reward_noise > 0.0:
            reward += self.model.reward_noise * float(self.np_random.standard_normal())
        self._state = int(sample_categorical(self.model.transitions[h, s, a][None],
                                             self.np_random)[0])
        self._h += 1
        truncated = self._h == self.model.horizon
        return self._state, reward, False, truncated, self._info()


class AmericanPutOptionEnv(_Base):
    """The :class:`~r2pvi.envs.AmericanPutOption` as a Gymnasium environment.

    The observation is the price, shape (1,). Exercising (action 1) pays
    ``max(0, strike - s)`` and terminates; holding pays 0 and moves the price.
    """

    metadata = {"render_modes": []}

    def __init__(self, model: AmericanPutOption):
        _require_gymnasium()
        if not isinstance(model, AmericanPutOption):
            raise TypeError(f"model must be an AmericanPutOption, got {type(model).__name__}")
        self.model = model
        lo, hi = model.price_range
        self.observation_space = spaces.Box(lo, hi, shape=(1,), dtype=np.float64)
        self.action_space = spaces.Discrete(2)
        self._h = None
        self._price = None
        self._done = False

    def _obs(self):
        return np.array([self._price], dtype=np.float64)

    def _info(self):
        price = np.array([self._price])
        known = self.model.known_values(price)[0]
        return {
            "step": self._h,
            "phi": self.model.phi_all(price)[0],
            "known": ~np.isnan(known),
            "known_values": np.nan_to_num(known),
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._h = 0
        self._done = False
        self._price = float(self.model.initial_prices(1, self.np_random)[0])
        return self._obs(), self._info()

    def step(self, action):
        if self._h is None:
            raise RuntimeError("call reset() before step()")
        if self._done or self._h >= self.model.H:
            raise RuntimeError("the episode is over: call reset()")
        a = _as_action(action, 2)
        self._h += 1
        if a == EXERCISE:
            self._done = True
            reward = float(self.model.payoff([self._price])[0])
            return self._obs(), reward, True, False, self._info()
        up = self.np_random.random() < self.model.p0
        self._price *= self.model.up if up else self.model.down
        truncated = self._h == self.model.H
        self._done = truncated
        return self._obs(), 0.0, False, truncated, self._info()


def greedy_action(estimator, info):
    """The action of a fitted estimator at the state described by a step's ``info``.

    Greedy on ``estimator.q_values(info["phi"], info["step"], known)`` with the known
    action values of ``info`` (ties go to the lowest action index). A single environment's
    ``info`` gives an ``int``; a vector environment's (``phi (n, A, d)``, ``step (n,)``)
    gives an ``(n,)`` array of actions, one per sub-environment.
    """
    phi = np.asarray(info["phi"], dtype=float)
    known = np.where(info["known"], info["known_values"], np.nan)
    if phi.ndim == 2:
        return int(estimator.act(phi[None], int(info["step"]), known[None])[0])
    steps = np.broadcast_to(np.asarray(info["step"]), phi.shape[:1])
    horizon = getattr(estimator, "horizon_", None)
    out = np.zeros(phi.shape[0], dtype=np.int64)
    for h in np.unique(steps):
        rows = steps == h
        if horizon is not None and h >= horizon:
            continue  # a finished sub-environment (autoreset pending): any action
        out[rows] = estimator.act(phi[rows], int(h), known[rows])
    return out


def _as_action(action, n_actions: int) -> int:
    arr = np.asarray(action)
    if arr.size != 1 or arr.dtype == bool or arr.dtype.kind not in "iu":
        raise TypeError(f"action must be an integer in [0, {n_actions}), got {action!r}")
    a = int(arr.reshape(()))
    if not 0 <= a < n_actions:
        raise ValueError(f"action must lie in [0, {n_actions}), got {a}")
    return a


def as_gymnasium_env(model):
    """Wrap an r2pvi environment as a Gymnasium environment (with a spec when possible).

    The spec (id and JSON-friendly kwargs) lets Minari record and recover the environment.
    """
    _require_gymnasium()
    register_envs()
    if isinstance(model, AmericanPutOption):
        env = AmericanPutOptionEnv(model)
    elif isinstance(model, FiniteLinearMDP):
        env = FiniteLinearMDPEnv(model)
    else:
        raise TypeError(
            "model must be a FiniteLinearMDP, SimulatedLinearMDP, HardInstance or "
            f"AmericanPutOption, got {type(model).__name__}"
        )
    env.spec = _spec_for(model)
    return env


def _spec_for(model):
    """An EnvSpec that rebuilds ``model`` through ``gymnasium.make``, or None."""
    kwargs = model.init_kwargs()
    try:  # the spec must survive JSON (Minari stores it) and rebuild the model
        kwargs = json.loads(json.dumps(kwargs))
        type(model)(**kwargs)
    except (TypeError, ValueError):
        return None
    base = gymnasium.spec(model.gym_id)
    return gymnasium.envs.registration.EnvSpec(
        id=base.id, entry_point=base.entry_point, kwargs=kwargs,
        disable_env_checker=base.disable_env_checker,
    )


# ---------------------------------------------------------------------- entry points
def make_finite_linear_mdp(**kwargs):
    """Entry point of ``r2pvi/FiniteLinearMDP-v0``."""
    return FiniteLinearMDPEnv(FiniteLinearMDP(**kwargs))


def make_simulated_linear_mdp(**kwargs):
    """Entry point of ``r2pvi/SimulatedLinearMDP-v0``."""
    return FiniteLinearMDPEnv(SimulatedLinearMDP(**kwargs))


def make_hard_instance(**kwargs):
    """Entry point of ``r2pvi/HardInstance-v0``."""
    return FiniteLinearMDPEnv(HardInstance(**kwargs))


def make_american_put_option(**kwargs):
    """Entry point of ``r2pvi/AmericanPutOption-v0``."""
    return AmericanPutOptionEnv(AmericanPutOption(**kwargs))


def register_envs() -> None:
    """Register the r2pvi ids with Gymnasium (idempotent; done on import)."""
    _require_gymnasium()
    for env_id, entry in _ENTRY_POINTS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=f"{__name__}:{entry}")
    if NOISY_CARTPOLE_ID not in gymnasium.registry:
        gymnasium.register(id=NOISY_CARTPOLE_ID,
                           entry_point="r2pvi.envs.noisy_cartpole_gym:NoisyCartPoleEnv")


if gymnasium is not None:
    register_envs()
