"""Monte Carlo evaluation of any policy in any Gymnasium environment (vectorized, seeded)."""

from __future__ import annotations

import warnings

import numpy as np

from ..envs.collect import run_episodes

__all__ = ["evaluate_policy", "episode_returns"]


def episode_returns(env, policy, n_episodes: int, *, seed=None, max_steps=None, n_envs=None,
                    reset_options=None, progress=None) -> np.ndarray:
    """The undiscounted return of each of ``n_episodes`` episodes, ``(n_episodes,)``.

    Same arguments as :func:`evaluate_policy`; episode ``i`` is the same whatever
    ``n_envs`` (see :mod:`r2pvi.envs.collect`).
    """
    return run_episodes(env, policy, n_episodes, seed=seed, max_steps=max_steps,
                        n_envs=n_envs, record=False, reset_options=reset_options,
                        progress=progress)


def evaluate_policy(env, policy, n_episodes: int, *, seed=None, max_steps=None, n_envs=None,
                    reset_options=None, progress=None) -> tuple[float, float]:
    """Monte Carlo estimate of a policy's expected return: ``(mean, standard error)``.

    Parameters
    ----------
    env : gymnasium.Env, gymnasium vector env, registered id or factory
        Evaluate under changed dynamics by passing a perturbed environment
        (:mod:`r2pvi.envs.perturbations`) or ``reset_options``.
    policy : callable, policy object or "uniform"
        ``policy(h, observations) -> actions`` on a batch (``estimator.as_policy(fmap)``),
        or a stochastic policy with ``sample(h, observations, rngs)``.
    n_episodes : int
    seed : int, SeedSequence or Generator, optional
        Episode ``i`` is seeded by ``SeedSequence(seed).spawn(n_episodes)[i]``.
    max_steps : int, optional
        Cut every episode after ``max_steps`` steps (the horizon H of a finite-horizon
        evaluation); None runs to the environment's own termination or time limit.
    n_envs : int, optional
        Sub-environments run in parallel (copies of ``env``); the result does not depend on it.
    reset_options : dict, optional
        Passed to every reset (RRLS-style parameters).
    progress : bool, optional
        A tqdm progress bar (None: on a terminal, for 100 episodes or more).

    Returns
    -------
    mean : float
    standard_error : float
        ``std(returns, ddof=1) / sqrt(n)`` (NaN for one episode, with a ``UserWarning``).

    Examples
    --------
    >>> import gymnasium as gym
    >>> import numpy as np
    >>> from r2pvi.evaluation import evaluate_policy
    >>> lean = lambda h, obs: (obs[:, 2] + obs[:, 3] > 0).astype(int)   # push toward the lean
    >>> mean, se = evaluate_policy(gym.make("CartPole-v1"), lean, 20, seed=0, max_steps=200,
    ...                            n_envs=4)
    >>> mean > 150, se >= 0
    (True, True)
    """
    returns = episode_returns(env, policy, n_episodes, seed=seed, max_steps=max_steps,
                              n_envs=n_envs, reset_options=reset_options, progress=progress)
    n = returns.shape[0]
    if n < 2:
        warnings.warn("evaluate_policy: one episode has no standard error (NaN is returned); "
                      "use n_episodes >= 2", UserWarning, stacklevel=2)
    se = float(returns.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    return float(returns.mean()), se
