"""Expected returns: exact (dynamic programming or lattice) and Monte Carlo."""

from __future__ import annotations

import numpy as np

from ..envs._sampling import check_count
from ..envs.finite import FiniteLinearMDP
from ..envs.put_option import AmericanPutOption
from .dynamic_programming import nominal_values
from .lattice import option_value

__all__ = ["expected_return", "monte_carlo_return"]


def expected_return(env, policy) -> float:
    """Exact expected (nominal) return of ``policy`` from the environment's start.

    Finite linear MDPs: dynamic programming, averaged over the initial distribution.
    Evaluate under a perturbation by passing the perturbed environment
    (``env.perturbed(q)``, ``env.with_factors(mu)``). American put option: the binomial
    lattice, integrated exactly over the uniform initial price (see
    :func:`~r2pvi.evaluation.option_value`).

    Parameters
    ----------
    env : FiniteLinearMDP or AmericanPutOption
    policy
        Finite models: an ``(H, S)`` array of actions, an ``(H, S, A)`` array of
        probabilities, a fitted estimator, a callable ``policy(h, states)`` or
        ``"uniform"``/``"behavior"``. Put option: a fitted estimator, a callable
        ``policy(h, prices) -> actions`` or ``"hold"``/``"exercise"``/``"uniform"``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.evaluation import expected_return
    >>> env = SimulatedLinearMDP()
    >>> best = np.full((3, 5), 15)                       # a = (1, 1, 1, 1) everywhere
    >>> round(expected_return(env, best), 6), round(expected_return(env.perturbed(0.5), best), 6)
    (1.62425, 1.124875)
    """
    if policy is None:
        raise TypeError(
            "expected_return needs a policy (an estimator, an action table, a callable or a "
            "name such as 'uniform'); for the optimal value use "
            "r2pvi.evaluation.nominal_values(env)"
        )
    if isinstance(env, AmericanPutOption):
        return float(option_value(env, policy))
    if isinstance(env, FiniteLinearMDP):
        _, V = nominal_values(env, policy)
        return float(env.initial @ V[0])
    raise TypeError(
        "env must be a FiniteLinearMDP (or SimulatedLinearMDP, HardInstance) or an "
        f"AmericanPutOption, got {type(env).__name__}"
    )


def monte_carlo_return(env, policy, n_episodes: int = 10_000, seed=None) -> tuple[float, float]:
    """Monte Carlo estimate of the expected return: ``(mean, standard error)``.

    Rollouts are vectorized over episodes (``env.simulate``) and seeded. ``n_episodes``
    must be at least 2 (the standard error needs two episodes).

    Examples
    --------
    >>> from r2pvi.envs import SimulatedLinearMDP
    >>> from r2pvi.evaluation import expected_return, monte_carlo_return
    >>> mean, se = monte_carlo_return(SimulatedLinearMDP(), "uniform", 20_000, seed=0)
    >>> bool(abs(mean - expected_return(SimulatedLinearMDP(), 'uniform')) < 4 * se)
    True
    """
    if not isinstance(env, FiniteLinearMDP | AmericanPutOption):
        raise TypeError(
            f"env must be a FiniteLinearMDP or an AmericanPutOption, got {type(env).__name__}"
        )
    if policy is None:
        raise TypeError("monte_carlo_return needs a policy, got None")
    n = check_count(n_episodes, "n_episodes")
    if n < 2:
        raise ValueError(
            f"n_episodes must be >= 2 (the standard error needs two episodes), got {n}"
        )
    returns = env.simulate(n, policy, seed).returns
    se = float(returns.std(ddof=1) / np.sqrt(n))
    return float(returns.mean()), se
