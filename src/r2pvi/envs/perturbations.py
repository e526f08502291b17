"""Perturbed dynamics for classic-control environments (optional extra ``gym``).

Robust RL evaluates a policy in environments whose physical parameters differ from the
nominal ones. Following RRLS (the Robust Reinforcement Learning Suite), parameters are read
with ``get_params()``, changed with ``set_params(**params)`` or passed at reset time,
``env.reset(seed=..., options={"gravity": 12.0})``, and stay until changed again. Every
constant the environment derives from a parameter is recomputed (CartPole's ``total_mass``
and ``polemass_length``; Pendulum's action and observation bounds), so a perturbed
environment steps exactly like one constructed with those parameters.

- :class:`PerturbedEnv` wraps CartPole (``gravity, masscart, masspole, length, force_mag,
  tau``), MountainCar (``force, gravity``), Acrobot (``link_length_1, link_mass_1,
  link_mass_2, link_com_pos_1, link_com_pos_2, link_moi``) and Pendulum (``g, m, l,
  max_torque, max_speed, dt``), and adds ``action_noise``: with probability ``p`` the
  executed action is a uniformly random one (drawn from a generator seeded at each seeded
  reset, so episodes are reproducible);
- :func:`make_perturbed` builds one from a Gymnasium id;
- :class:`DiscreteTorque` makes Pendulum's torque discrete (``n`` levels in
  ``[-max_torque, max_torque]``, following ``max_torque`` when it is perturbed).

Examples
--------
>>> from r2pvi.envs.perturbations import make_perturbed
>>> env = make_perturbed("CartPole-v1", length=1.0)             # a pole twice as long
>>> p = env.get_params()
>>> p["length"], round(env.unwrapped.polemass_length, 6)
(1.0, 0.1)
>>> _ = env.reset(seed=0, options={"force_mag": 20.0})          # RRLS: parameters at reset
>>> env.get_params()["force_mag"]
20.0
"""

from __future__ import annotations

import numbers

import numpy as np

try:  # the optional extra
    import gymnasium
    from gymnasium.utils import RecordConstructorArgs
except ImportError:  # pragma: no cover - exercised only without the extra
    gymnasium = None
    RecordConstructorArgs = object

__all__ = [
    "PerturbedEnv",
    "make_perturbed",
    "set_env_params",
    "DiscreteTorque",
    "PARAMETERS",
    "nominal_params",
]

#: The parameters each environment class accepts: name -> attribute of the unwrapped env.
PARAMETERS = {
    "CartPoleEnv": {
        "gravity": "gravity", "masscart": "masscart", "masspole": "masspole",
        "length": "length", "force_mag": "force_mag", "tau": "tau",
    },
    "CartPoleVectorEnv": {
        "gravity": "gravity", "masscart": "masscart", "masspole": "masspole",
        "length": "length", "force_mag": "force_mag", "tau": "tau",
    },
    "MountainCarEnv": {"force": "force", "gravity": "gravity"},
    "AcrobotEnv": {
        "link_length_1": "LINK_LENGTH_1", "link_mass_1": "LINK_MASS_1",
        "link_mass_2": "LINK_MASS_2", "link_com_pos_1": "LINK_COM_POS_1",
        "link_com_pos_2": "LINK_COM_POS_2", "link_moi": "LINK_MOI",
    },
    "PendulumEnv": {
        "g": "g", "m": "m", "l": "l", "max_torque": "max_torque", "max_speed": "max_speed",
        "dt": "dt",
    },
}
# Parameters that must be > 0 (others, like gravity, may be any finite number, 0 included).
_POSITIVE = {"masscart", "masspole", "length", "tau", "link_length_1", "link_mass_1",
             "link_mass_2", "link_moi", "m", "l", "max_torque", "max_speed", "dt"}
ACTION_NOISE = "action_noise"


def _require_gymnasium():
    if gymnasium is None:
        raise ImportError(
            "perturbed environments need gymnasium: pip install 'r2pvi[gym]'"
        )


def _table(unwrapped) -> dict:
    for cls in type(unwrapped).__mro__:
        if cls.__name__ in PARAMETERS:
            return PARAMETERS[cls.__name__]
    raise TypeError(
        f"no known physical parameters for {type(unwrapped).__name__}; supported: "
        f"{', '.join(PARAMETERS)} (action_noise works with any Discrete action space)"
    )


def _recompute_derived(unwrapped) -> None:
    """Constants the environment computes from its parameters in ``__init__``."""
    name = type(unwrapped).__name__
    if "CartPole" in name:
        unwrapped.total_mass = unwrapped.masspole + unwrapped.masscart
        unwrapped.polemass_length = unwrapped.masspole * unwrapped.length
    elif "Pendulum" in name:
        from gymnasium import spaces

        high = np.array([1.0, 1.0, unwrapped.max_speed], dtype=np.float32)
        unwrapped.action_space = spaces.Box(
            low=-unwrapped.max_torque, high=unwrapped.max_torque, shape=(1,), dtype=np.float32
        )
        unwrapped.observation_space = spaces.Box(low=-high, high=high, dtype=np.float32)


def set_env_params(env, **params) -> None:
    """Set physical parameters of ``env`` in place (absolute values) and recompute the
    constants derived from them.

    Works on any wrapping of a supported environment and on Gymnasium's own vectorized
    ``CartPoleVectorEnv`` (``gym.make_vec("CartPole-v1", n,
    vectorization_mode="vector_entry_point")``), whose parameters are shared by all its
    sub-environments. For action noise, wrap single environments in :class:`PerturbedEnv`.

    Examples
    --------
    >>> import gymnasium as gym
    >>> from r2pvi.envs.perturbations import set_env_params
    >>> venv = gym.make_vec("CartPole-v1", 4, vectorization_mode="vector_entry_point")
    >>> set_env_params(venv, masspole=0.2, length=1.0)
    >>> round(venv.unwrapped.polemass_length, 6), round(venv.unwrapped.total_mass, 6)
    (0.2, 1.2)
    """
    if ACTION_NOISE in params:
        raise ValueError("action_noise is not a physical parameter: use PerturbedEnv")
    unwrapped = env.unwrapped
    table = _table(unwrapped)
    unknown = sorted(set(params) - set(table))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {unknown} for {type(unwrapped).__name__}; valid: "
            f"{sorted(table) + [ACTION_NOISE]}"
        )
    checked = {k: _check_value(k, v) for k, v in params.items()}
    for k, v in checked.items():
        setattr(unwrapped, table[k], v)
    _recompute_derived(unwrapped)


def nominal_params(env) -> dict:
    """The current physical parameters of ``env`` (any wrapper of a supported env)."""
    unwrapped = env.unwrapped
    return {k: float(getattr(unwrapped, attr)) for k, attr in _table(unwrapped).items()}


def _check_value(name, value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"parameter {name} must be a real number, got {value!r}")
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"parameter {name} must be finite, got {value!r}")
    if name in _POSITIVE and v <= 0:
        raise ValueError(f"parameter {name} must be > 0, got {value!r}")
    if name == ACTION_NOISE and not 0.0 <= v <= 1.0:
        raise ValueError(f"action_noise must be a probability in [0, 1], got {value!r}")
    return v


_Base = gymnasium.Wrapper if gymnasium is not None else object


class PerturbedEnv(_Base, RecordConstructorArgs):
    """An environment with changed physical parameters and optional action noise.

    Parameters
    ----------
    env : gymnasium.Env
        CartPole, MountainCar, Acrobot or Pendulum (any wrapping), or any environment with a
        Discrete action space when only ``action_noise`` is used.
    action_noise : float in [0, 1], default 0
        Probability that the executed action is uniformly random instead of the chosen one.
    **params
        Physical parameters (see :data:`PARAMETERS`), absolute values; multiply
        :func:`nominal_params` for relative perturbations.

    Notes
    -----
    ``reset(options={...})`` applies the parameters (and ``action_noise``) found in
    ``options`` before resetting; other options go to the wrapped environment. The wrapper
    records its arguments, so ``gymnasium.make(env.spec)`` rebuilds it.
    """

    def __init__(self, env, *, action_noise: float = 0.0, **params):
        _require_gymnasium()
        RecordConstructorArgs.__init__(self, action_noise=action_noise, **params)
        gymnasium.Wrapper.__init__(self, env)
        self._noise = 0.0
        self._noise_rng = np.random.default_rng()
        self._nominal = None
        if params:
            self._nominal = nominal_params(env)
        self.set_params(action_noise=action_noise, **params)

    # ------------------------------------------------------------------ RRLS interface
    def get_params(self) -> dict:
        """Current parameters (physical ones when the environment is supported)."""
        try:
            out = nominal_params(self.env)
        except TypeError:
            out = {}
        out[ACTION_NOISE] = self._noise
        return out

    def set_params(self, **params) -> None:
        """Change parameters (absolute values); derived constants are recomputed."""
        physical = {k: v for k, v in params.items() if k != ACTION_NOISE}
        noise = None
        if ACTION_NOISE in params:
            noise = _check_value(ACTION_NOISE, params[ACTION_NOISE])
            if noise > 0 and not hasattr(self.env.action_space, "n"):
                raise TypeError("action_noise needs a Discrete action space")
        if physical:
            set_env_params(self.env, **physical)
        if noise is not None:
            self._noise = noise

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed=None, options=None):
        rest = None
        if options:
            mine = {k: v for k, v in options.items() if k == ACTION_NOISE or k in _maybe_table(
                self.env.unwrapped)}
            rest = {k: v for k, v in options.items() if k not in mine} or None
            if mine:
                self.set_params(**mine)
        if seed is not None:
            self._noise_rng = np.random.default_rng([int(seed) % 2**63, 0x4E015E])
        return self.env.reset(seed=seed, options=rest)

    def step(self, action):
        if self._noise > 0.0 and self._noise_rng.random() < self._noise:
            space = self.env.action_space
            action = np.int64(space.start + self._noise_rng.integers(space.n))
        return self.env.step(action)


def _maybe_table(unwrapped) -> dict:
    try:
        return _table(unwrapped)
    except TypeError:
        return {}


def make_perturbed(env_id: str, *, action_noise: float = 0.0, make_kwargs=None, **params):
    """``PerturbedEnv(gymnasium.make(env_id, **make_kwargs), action_noise=..., **params)``.

    Examples
    --------
    >>> from r2pvi.envs.perturbations import make_perturbed
    >>> env = make_perturbed("MountainCar-v0", force=0.0008, action_noise=0.1)
    >>> env.get_params()["force"], env.get_params()["action_noise"]
    (0.0008, 0.1)
    """
    _require_gymnasium()
    env = gymnasium.make(env_id, **(make_kwargs or {}))
    return PerturbedEnv(env, action_noise=action_noise, **params)


_ActionBase = gymnasium.ActionWrapper if gymnasium is not None else object


class DiscreteTorque(_ActionBase, RecordConstructorArgs):
    """Pendulum with ``n_levels`` torques evenly spaced in ``[-max_torque, max_torque]``.

    The levels follow ``max_torque`` when it is perturbed (they are computed at each step).

    Examples
    --------
    >>> import gymnasium as gym
    >>> from r2pvi.envs.perturbations import DiscreteTorque
    >>> env = DiscreteTorque(gym.make("Pendulum-v1"), n_levels=5)
    >>> env.action_space, env.action(4)
    (Discrete(5), array([2.], dtype=float32))
    """

    def __init__(self, env, n_levels: int = 5):
        _require_gymnasium()
        if isinstance(n_levels, bool) or not isinstance(n_levels, numbers.Integral) or (
            n_levels < 2
        ):
            raise ValueError(f"n_levels must be an integer >= 2, got {n_levels!r}")
        RecordConstructorArgs.__init__(self, n_levels=n_levels)
        gymnasium.ActionWrapper.__init__(self, env)
        self.n_levels = int(n_levels)
        self.action_space = gymnasium.spaces.Discrete(self.n_levels)

    def action(self, action):
        top = float(self.env.unwrapped.max_torque)
        level = int(np.asarray(action).reshape(()))
        torque = -top + 2.0 * top * level / (self.n_levels - 1)
        return np.array([torque], dtype=np.float32)
