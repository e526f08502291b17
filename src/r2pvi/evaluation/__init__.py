"""Exact evaluation: nominal, perturbed, robust-regularized and constrained values.

Finite linear MDPs are evaluated by dynamic programming that reuses the duals of
:mod:`r2pvi.duals` with the true factor distributions (``FactorExpectation(mu_h)``); the
American put option on its binomial lattice, integrated exactly over the initial price.
Monte Carlo rollouts are here too, to check the exact numbers, and Monte Carlo evaluation of
any policy in any Gymnasium environment (:func:`evaluate_policy`).
"""

from .dynamic_programming import (
    constrained_values,
    greedy_policy,
    nominal_values,
    optimal_policy,
    robust_values,
)
from .lattice import option_value
from .returns import expected_return, monte_carlo_return
from .rollouts import episode_returns, evaluate_policy
from .suboptimality import suboptimality

__all__ = [
    "expected_return",
    "monte_carlo_return",
    "nominal_values",
    "robust_values",
    "constrained_values",
    "optimal_policy",
    "greedy_policy",
    "suboptimality",
    "option_value",
    "evaluate_policy",
    "episode_returns",
]
