"""The test grid of the noisy CartPole protocol (RFQI / RFZI), evaluated in one batch.

A policy is tested in CartPoles whose parameters are scaled by ``1 + p``:

- ``force_mag`` and pole ``length``: ``p = -0.8, -0.4, ..., 3.6`` (12 values each);
- ``gravity``: ``p = -3.0, -2.5, ..., 2.5`` (12 values; ``p < -1`` turns gravity upward);

36 points, 20 test episodes each, with common random numbers: episode ``e`` has the same
initial state, dynamics noise and policy random numbers at every point (and for every
policy evaluated with the same seed). :func:`evaluate_cartpole_grid` runs all
``36 x 20`` episodes as one :class:`~r2pvi.envs.noisy_cartpole.NoisyCartPoleBatch`.

Examples
--------
>>> from r2pvi.envs import evaluate_cartpole_grid
>>> from r2pvi.envs.experts import CartPoleLQR
>>> result = evaluate_cartpole_grid(CartPoleLQR())       # seed 0, 20 episodes a point
>>> len(result.p), result.returns.shape
(36, (36, 20))
>>> row = result.rows()[0]
>>> row["parameter"], row["p"], round(row["value"], 12)       # 10 x (1 - 0.8)
('force_mag', -0.8, 2.0)
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from ._sampling import check_count
from .noisy_cartpole import (
    MAX_STEPS,
    NOMINAL,
    SIGMA,
    NoisyCartPoleBatch,
    _check_actions,
    check_cartpole_params,
    episode_streams,
)
from .rollout_policies import as_policy_function

__all__ = ["evaluate_cartpole_grid", "perturbation_grid", "GridEvaluation", "PROTOCOL_GRID",
           "TEST_EPISODES"]

#: The published test grid: parameter -> the relative changes ``p`` (value ``x (1 + p)``).
PROTOCOL_GRID = {
    "force_mag": tuple((np.arange(12) * 2 - 4) / 5),    # -0.8, -0.4, ..., 3.6
    "gravity": tuple((np.arange(12) - 6) / 2),          # -3.0, -2.5, ..., 2.5
    "length": tuple((np.arange(12) * 2 - 4) / 5),       # -0.8, -0.4, ..., 3.6
}
TEST_EPISODES = 20


def perturbation_grid(grid=None, **base):
    """The grid points: ``(parameters, p, values)``, three ``(K,)`` arrays.

    Parameters
    ----------
    grid : dict, optional
        Parameter name -> sequence of relative changes ``p``; :data:`PROTOCOL_GRID` by
        default (36 points).
    **base
        Parameters to scale (Gymnasium's nominal values by default).

    Examples
    --------
    >>> from r2pvi.envs.cartpole_grid import perturbation_grid
    >>> names, p, values = perturbation_grid()
    >>> len(p), values[names == "gravity"][[0, -1]].round(2).tolist()
    (36, [-19.6, 34.3])
    """
    grid = PROTOCOL_GRID if grid is None else grid
    if not isinstance(grid, dict) or not grid:
        raise TypeError(f"grid must be a non-empty dict parameter -> sequence of p, got {grid!r}")
    base = {**NOMINAL, **check_cartpole_params(base)}
    names, ps, values = [], [], []
    for name, changes in grid.items():
        if name not in NOMINAL:
            raise ValueError(f"grid: unknown CartPole parameter {name!r}; valid: "
                             f"{sorted(NOMINAL)}")
        for p in np.atleast_1d(np.asarray(changes, dtype=float)):
            value = base[name] * (1.0 + p)
            check_cartpole_params({name: value})  # names the parameter (length x (1 - 1))
            names.append(name)
            ps.append(float(p))
            values.append(float(value))
    return np.array(names), np.array(ps), np.array(values)


@dataclass(frozen=True, eq=False)
class GridEvaluation:
    """Returns of a policy on a test grid.

    Attributes
    ----------
    parameter : ndarray (K,) of str
        The parameter changed at each point.
    p : ndarray (K,)
        Its relative change (the value is the base value ``x (1 + p)``).
    value : ndarray (K,)
        Its value.
    returns : ndarray (K, E)
        The return of each test episode (episode ``e`` is the same at every point).
    """

    parameter: np.ndarray
    p: np.ndarray
    value: np.ndarray
    returns: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        """Mean return at each point ``(K,)``."""
        return self.returns.mean(axis=1)

    @property
    def std(self) -> np.ndarray:
        """Standard deviation of the returns at each point (``ddof=0``, as published)."""
        return self.returns.std(axis=1)

    @property
    def se(self) -> np.ndarray:
        """Standard error of the mean at each point (``ddof=1``; NaN for one episode)."""
        n = self.returns.shape[1]
        if n < 2:
            return np.full(len(self.p), np.nan)
        return self.returns.std(axis=1, ddof=1) / np.sqrt(n)

    def rows(self) -> list[dict]:
        """One dict a point: ``parameter, p, value, mean, std, se`` (a tidy table:
        ``pandas.DataFrame(result.rows())``)."""
        mean, std, se = self.mean, self.std, self.se
        return [{"parameter": str(self.parameter[k]), "p": float(self.p[k]),
                 "value": float(self.value[k]), "mean": float(mean[k]),
                 "std": float(std[k]), "se": float(se[k])} for k in range(len(self.p))]

    def sweep(self, parameter: str):
        """``(p, mean, std)`` of one parameter's points, for a plot."""
        rows = self.parameter == parameter
        if not rows.any():
            raise ValueError(f"parameter {parameter!r} is not on the grid; it has "
                             f"{sorted(set(self.parameter.tolist()))}")
        return self.p[rows], self.mean[rows], self.std[rows]

    def __str__(self) -> str:
        lines = [f"{'parameter':<10} {'p':>5} {'value':>8} {'mean':>7} {'std':>6}"]
        lines += [f"{r['parameter']:<10} {r['p']:>5.1f} {r['value']:>8.3g} {r['mean']:>7.1f} "
                  f"{r['std']:>6.1f}" for r in self.rows()]
        return "\n".join(lines)


def evaluate_cartpole_grid(policy, *, n_episodes: int = TEST_EPISODES, seed=0, grid=None,
                           sigma=SIGMA, max_steps: int = MAX_STEPS, **base) -> GridEvaluation:
    """Evaluate ``policy`` at every grid point, all episodes in one vectorized rollout.

    Parameters
    ----------
    policy : callable, policy object or "uniform"
        ``policy(h, observations) -> actions`` on a batch (``observations (n, 4)`` float32,
        ``h (n,)`` the step), such as a fitted estimator's ``as_policy(feature_map)`` or
        :class:`~r2pvi.envs.experts.CartPoleLQR`; or a stochastic policy with
        ``sample(h, observations, rngs)`` (:class:`~r2pvi.envs.EpsilonGreedy`).
    n_episodes : int, default 20
        Test episodes a point.
    seed : int or SeedSequence, default 0
        Episode ``e`` uses ``SeedSequence(seed).spawn(n_episodes)[e]`` at every point
        (common random numbers), the seeds :func:`r2pvi.evaluation.evaluate_policy` gives
        its episode ``e``: a point's returns are those of ``evaluate_policy`` in
        ``NoisyCartPoleEnv`` with that point's parameters. A fixed default, so that two
        policies are compared on the same episodes.
    grid : dict, optional
        Parameter -> relative changes ``p``; :data:`PROTOCOL_GRID` by default.
    sigma : float, default 0.1
    max_steps : int, default 200
    **base
        Parameters the grid scales and the other points keep (nominal by default).

    Returns
    -------
    GridEvaluation
        ``parameter, p, value`` and ``returns (K, n_episodes)``; ``mean``, ``std``, ``se``
        and ``rows()``.
    """
    n_episodes = check_count(n_episodes, "n_episodes")
    names, ps, values = perturbation_grid(grid, **base)
    K, E = len(ps), n_episodes
    params = {k: np.full(K * E, v, dtype=float) for k, v in
              {**NOMINAL, **check_cartpole_params(base)}.items()}
    for k, (name, value) in enumerate(zip(names, values, strict=True)):
        params[name][k * E:(k + 1) * E] = value
    batch = NoisyCartPoleBatch(K * E, sigma=sigma, max_steps=max_steps, **params)
    act = as_policy_function(policy, 2)
    initial, noise, _, rngs = episode_streams(seed, E, batch.max_steps)
    episodes = np.tile(np.arange(E), K)
    row_rngs = [copy.deepcopy(rngs[e]) for e in episodes]
    obs = batch.start(initial, noise, episodes)
    returns = np.zeros(K * E)
    actions = np.zeros(K * E, dtype=np.int64)
    for t in range(batch.max_steps):
        live = np.flatnonzero(~batch.done)
        if live.size == 0:
            break
        a = act(np.full(live.size, t), obs[live], [row_rngs[i] for i in live])
        actions[live] = _check_actions(a, live.size, slice(None), "the policy's actions")
        obs, rewards, _, _ = batch.step(actions)
        returns += rewards
    return GridEvaluation(parameter=names, p=ps, value=values,
                          returns=returns.reshape(K, E))
