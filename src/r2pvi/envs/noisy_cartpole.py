"""The noisy CartPole of robust offline RL (RFQI, Panaganti et al. 2022), vectorized in NumPy.

The protocol of "Robust Reinforcement Learning using Offline Data" (Panaganti, Xu, Kalathil
and Ghavamzadeh, NeurIPS 2022) and of the later RFZI experiments changes Gymnasium's
CartPole in three ways:

- **dynamics noise**: ``sigma * N(0, 1)`` is added to the denominator of the pole's angular
  acceleration, ``l (4/3 - m_p cos^2(theta) / (m_c + m_p)) + sigma eps_1``, and to the
  cart's acceleration, ``x_acc + sigma eps_2``; ``sigma = 0.1``;
- **initial states** ``theta ~ U(-0.2, 0.2)``, the other three components ``~ U(-0.05,
  0.05)``;
- **200 steps** at most; Euler steps of ``tau = 0.02``, failure when ``|x| > 2.4`` or
  ``|theta| > 12`` degrees, reward 1 per step including the failing one (as Gymnasium).

:class:`NoisyCartPoleBatch` steps ``n`` such CartPoles together, each with its own
parameters (a whole test grid is one batch); :func:`cartpole_step` is its one Euler step.
Episode ``e`` of a seed draws its initial state and its noise from its own
``numpy.random.Generator`` (4 uniforms, then 2 normals per step), so rows that run the
same episode see the same initial state and noise whatever their parameters (common random
numbers). :class:`~r2pvi.envs.noisy_cartpole_gym.NoisyCartPoleEnv` (extra ``gym``) is the
single Gymnasium environment with the same streams: ``reset(seed=s)`` runs the episode whose
generator is ``numpy.random.default_rng(s)``. The test grid and its evaluation are in
:mod:`r2pvi.envs.cartpole_grid`.

Examples
--------
>>> import numpy as np
>>> from r2pvi.envs.noisy_cartpole import NoisyCartPoleBatch
>>> batch = NoisyCartPoleBatch(3, length=np.array([0.1, 0.5, 2.3]))
>>> obs = batch.reset(seed=0, episodes=[0, 0, 0])      # one episode, three pole lengths
>>> bool((obs == obs[0]).all())                        # the same initial state
True
>>> obs, reward, terminated, truncated = batch.step(np.array([1, 1, 1]))
>>> reward.tolist(), obs.dtype
([1.0, 1.0, 1.0], dtype('float32'))
"""

from __future__ import annotations

import math

import numpy as np

from ._sampling import check_count
from .collect import episode_seeds

__all__ = [
    "NoisyCartPoleBatch",
    "cartpole_step",
    "failed",
    "initial_states",
    "episode_streams",
    "check_cartpole_params",
    "NOMINAL",
    "SIGMA",
    "MAX_STEPS",
    "INITIAL_HIGH",
]

#: Gymnasium's nominal CartPole parameters (``length`` is half the pole's length).
NOMINAL = {"gravity": 9.8, "masscart": 1.0, "masspole": 0.1, "length": 0.5,
           "force_mag": 10.0, "tau": 0.02}
#: The protocol's dynamics noise, episode length and initial-state half-widths
#: ``(x, x_dot, theta, theta_dot)``.
SIGMA = 0.1
MAX_STEPS = 200
INITIAL_HIGH = np.array([0.05, 0.05, 0.2, 0.05])
X_THRESHOLD = 2.4
THETA_THRESHOLD = 12 * 2 * math.pi / 360  # Gymnasium's expression, bit for bit
_POSITIVE = ("masscart", "masspole", "length", "tau")



# ---------------------------------------------------------------------- parameters
def _real_array(name, value, n=None) -> np.ndarray:
    if isinstance(value, bool | np.bool_) or isinstance(value, str):
        raise TypeError(f"{name} must be a real number or an array of them, got {value!r}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number or an array of them, got {value!r}"
                        ) from None
    if (arr.ndim != 0 if n is None else arr.ndim > 1 or arr.size not in (1, n)):
        want = "a scalar" if n is None else f"a scalar or an array of shape ({n},)"
        raise ValueError(f"{name} must be {want}, got shape {arr.shape}")
    return arr


def check_cartpole_params(params: dict, n=None) -> dict:
    """Checked physical parameters and ``sigma``: floats, or ``(n,)`` float arrays when
    ``n`` is given.

    Raises ``ValueError`` naming the parameter: unknown names, non-finite values,
    ``masscart, masspole, length, tau <= 0`` or ``sigma < 0`` (``gravity`` and
    ``force_mag`` may be any finite number).
    """
    valid = sorted(NOMINAL) + ["sigma"]
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(f"unknown CartPole parameter(s) {unknown}; valid: {valid}")
    out = {}
    for name, value in params.items():
        arr = _real_array(name, value, n)
        if not np.isfinite(arr).all():
            raise ValueError(f"parameter {name} must be finite, got {value!r}")
        if name in _POSITIVE and (arr <= 0).any():
            raise ValueError(f"parameter {name} must be > 0, got {value!r}")
        if name == "sigma" and (arr < 0).any():
            raise ValueError(f"parameter sigma (the noise scale) must be >= 0, got {value!r}")
        out[name] = float(arr) if arr.ndim == 0 else arr.copy()
    return out


# ---------------------------------------------------------------------- dynamics
def cartpole_step(state, actions, *, gravity=9.8, masscart=1.0, masspole=0.1, length=0.5,
                  force_mag=10.0, tau=0.02, sigma=0.0, noise=None) -> np.ndarray:
    """One Euler step of ``n`` CartPoles: the next states ``(n, 4)``.

    Gymnasium's equations (the same operations in the same order, so ``sigma = 0`` gives
    Gymnasium's step), with ``sigma * noise[:, 0]`` added to the denominator of the
    angular acceleration and ``sigma * noise[:, 1]`` to the cart's acceleration.

    Parameters
    ----------
    state : array (n, 4)
        ``(x, x_dot, theta, theta_dot)`` of each CartPole.
    actions : array (n,)
        1 pushes right (``+force_mag``), anything else left.
    gravity, masscart, masspole, length, force_mag, tau : float or array (n,)
        Unchecked here (see :func:`check_cartpole_params`).
    sigma : float or array (n,)
    noise : array (n, 2), optional
        Standard normal draws; None is no noise.

    Notes
    -----
    A noise draw near ``-l (4/3 - ...) / sigma`` can send the state to infinity or NaN
    (no warning); :func:`failed` counts such a state as a failure.
    """
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        return _euler(np.asarray(state, dtype=float), np.asarray(actions), gravity, masscart,
                      masspole, length, force_mag, tau, sigma, noise)


def _euler(state, actions, gravity, masscart, masspole, length, force_mag, tau, sigma, noise):
    x, x_dot, theta, theta_dot = state.T
    force = np.where(actions == 1, force_mag, -force_mag)
    costheta, sintheta = np.cos(theta), np.sin(theta)
    total_mass = masspole + masscart
    polemass_length = masspole * length
    temp = (force + polemass_length * np.square(theta_dot) * sintheta) / total_mass
    denominator = length * (4.0 / 3.0 - masspole * np.square(costheta) / total_mass)
    if noise is not None:
        denominator = denominator + sigma * noise[:, 0]
    thetaacc = (gravity * sintheta - costheta * temp) / denominator
    xacc = temp - polemass_length * thetaacc * costheta / total_mass
    if noise is not None:
        xacc = xacc + sigma * noise[:, 1]
    return np.stack([x + tau * x_dot, x_dot + tau * xacc, theta + tau * theta_dot,
                     theta_dot + tau * thetaacc], axis=1)


def failed(state) -> np.ndarray:
    """``(n,)`` True where ``|x| > 2.4`` or ``|theta| > 12`` degrees (or the state is NaN)."""
    state = np.asarray(state)
    return ~(np.abs(state[:, 0]) <= X_THRESHOLD) | ~(np.abs(state[:, 2]) <= THETA_THRESHOLD)


def initial_states(uniforms) -> np.ndarray:
    """Initial states from ``U[0, 1)`` draws ``(..., 4)``: ``INITIAL_HIGH * (2 u - 1)``."""
    return INITIAL_HIGH * (2.0 * np.asarray(uniforms, dtype=float) - 1.0)


def episode_streams(seed, n_episodes: int, max_steps: int):
    """``(initial (E, 4), noise (E, max_steps, 2), env_seeds (E,), policy_rngs)``.

    Episode ``e``'s generator is ``default_rng(env_seeds[e])`` with ``env_seeds`` from
    :func:`r2pvi.envs.collect.episode_seeds` (as for :func:`r2pvi.evaluation.evaluate_policy`);
    it draws 4 uniforms (the initial state), then 2 normals per step.
    """
    seeds, rngs = episode_seeds(seed, n_episodes)
    initial = np.empty((n_episodes, 4))
    noise = np.empty((n_episodes, max_steps, 2))
    for e, s in enumerate(seeds):
        gen = np.random.default_rng(int(s))
        initial[e] = initial_states(gen.random(4))
        noise[e] = gen.standard_normal((max_steps, 2))
    return initial, noise, seeds, rngs


# ---------------------------------------------------------------------- the batch
class NoisyCartPoleBatch:
    """``n`` noisy CartPoles stepped together, each with its own parameters.

    Parameters
    ----------
    n_envs : int
    sigma : float or array (n,), default 0.1
        Scale of the dynamics noise (0: Gymnasium's deterministic CartPole).
    max_steps : int, default 200
        Episodes are truncated after this many steps.
    **params
        ``gravity, masscart, masspole, length, force_mag, tau`` (Gymnasium's nominal
        values by default): a float for every row or an ``(n,)`` array, one per row.

    Attributes
    ----------
    state : ndarray (n, 4)
        The float64 states (observations are their float32 copies, as in Gymnasium).
    done : ndarray (n,) of bool
        Rows whose episode has ended; they no longer move and earn 0.
    t : int
        Steps taken since :meth:`reset`.
    params : dict of ndarray (n,)
    """

    def __init__(self, n_envs: int, *, sigma=SIGMA, max_steps: int = MAX_STEPS, **params):
        self.n_envs = check_count(n_envs, "n_envs")
        self.max_steps = check_count(max_steps, "max_steps")
        checked = check_cartpole_params({**NOMINAL, **params, "sigma": sigma}, self.n_envs)
        full = {k: np.broadcast_to(v, (self.n_envs,)).astype(float) for k, v in checked.items()}
        self.sigma = full.pop("sigma")
        self.params = full
        self.state = None
        self.done = None
        self.t = 0
        self._episodes = None
        self._noise = None

    def reset(self, seed=None, *, episodes=None) -> np.ndarray:
        """Start every row's episode; returns the observations ``(n, 4)`` float32.

        Parameters
        ----------
        seed : None, int, SeedSequence or Generator
            Episode ``e`` draws from the generator of
            ``SeedSequence(seed).spawn(E)[e]`` (see :func:`episode_streams`).
        episodes : array (n,) of int, optional
            The episode each row runs (default: row ``i`` runs episode ``i``). Rows with the
            same episode share its initial state and noise (common random numbers).
        """
        episodes = self._check_episodes(episodes)
        initial, noise, _, _ = episode_streams(seed, int(episodes.max()) + 1, self.max_steps)
        return self.start(initial, noise, episodes)

    def start(self, initial, noise, episodes=None) -> np.ndarray:
        """Start from given streams: row ``i`` runs episode ``episodes[i]``, from
        ``initial[episodes[i]]`` with the standard normals ``noise[episodes[i]]``
        ``(max_steps, 2)``; returns the observations ``(n, 4)`` float32."""
        episodes = self._check_episodes(episodes)
        initial = np.asarray(initial, dtype=float)
        noise = np.asarray(noise, dtype=float)
        E = int(episodes.max()) + 1
        if initial.ndim != 2 or initial.shape[1] != 4 or initial.shape[0] < E:
            raise ValueError(f"initial must have shape (E, 4) with E >= {E}, got "
                             f"{initial.shape}")
        if noise.shape != (initial.shape[0], self.max_steps, 2):
            raise ValueError(f"noise must have shape ({initial.shape[0]}, {self.max_steps}, "
                             f"2) (episodes, max_steps, 2), got {noise.shape}")
        self._episodes = episodes
        self._noise = noise
        self.state = initial[episodes]
        self.done = np.zeros(self.n_envs, dtype=bool)
        self.t = 0
        return self.state.astype(np.float32)

    def _check_episodes(self, episodes) -> np.ndarray:
        if episodes is None:
            return np.arange(self.n_envs)
        arr = np.asarray(episodes)
        if arr.shape != (self.n_envs,) or arr.dtype.kind not in "iu" or arr.min() < 0:
            raise ValueError(f"episodes must be {self.n_envs} non-negative integers (one per "
                             f"row), got {episodes!r}")
        return arr.astype(np.intp)

    def step(self, actions):
        """Step the rows still running: ``(obs, rewards, terminated, truncated)``, each
        ``(n,)`` (``obs (n, 4)`` float32); finished rows keep their state and earn 0.

        ``actions`` holds one action in {0, 1} per row (ignored for finished rows).
        """
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        if self.done.all():
            raise RuntimeError("every episode is over: call reset()")
        live = ~self.done
        a = _check_actions(actions, self.n_envs, live)
        rows = np.flatnonzero(live)
        p = {k: v[rows] for k, v in self.params.items()}
        noise = self._noise[self._episodes[rows], self.t]
        nxt = cartpole_step(self.state[rows], a[rows], sigma=self.sigma[rows], noise=noise, **p)
        self.state[rows] = nxt
        self.t += 1
        rewards = live.astype(float)
        terminated = np.zeros(self.n_envs, dtype=bool)
        terminated[rows] = failed(nxt)
        truncated = live & ~terminated & (self.t >= self.max_steps)
        self.done |= terminated | truncated
        return self.state.astype(np.float32), rewards, terminated, truncated

    def __repr__(self) -> str:
        return f"NoisyCartPoleBatch({self.n_envs}, max_steps={self.max_steps})"


def _check_actions(actions, n: int, live, who: str = "actions") -> np.ndarray:
    a = np.asarray(actions)
    if a.shape != (n,):
        raise ValueError(f"{who} must have shape ({n},) (one per row), got {a.shape}")
    if a.dtype.kind not in "iuf" or not np.isin(a[live], (0, 1)).all():
        bad = a[live][~np.isin(a[live], (0, 1))] if a.dtype.kind in "iuf" else a[live]
        raise ValueError(f"{who} must be 0 (push left) or 1 (push right), got {bad[:5]!r}")
    return a
