"""Environments: finite linear MDPs with explicit factors and the paper's benchmarks.

- :class:`FiniteLinearMDP` — any finite d-rectangular linear MDP
  ``P_h(s'|s,a) = sum_i phi_i(s,a) mu_{h,i}(s')``;
- :class:`SimulatedLinearMDP` — the paper's simulated linear MDP (Appendix A.1);
- :class:`HardInstance` — the hard instances of the lower bound;
- :class:`AmericanPutOption` — the simulated American put option (Appendix A.2).
- :func:`evaluate_cartpole_grid` — the noisy CartPole test grid of RFQI (vectorized NumPy;
  :mod:`r2pvi.envs.noisy_cartpole`).

Each collects offline datasets exactly as the paper does (``env.collect``). Exact
evaluation lives in :mod:`r2pvi.evaluation`. The Gymnasium adapters (:mod:`r2pvi.envs.gym`,
extra ``gym``) and the Minari import/export (:mod:`r2pvi.envs.minari`, extra ``minari``) are
imported only when used.
"""

from ._dataset import Trajectories
from .cartpole_grid import GridEvaluation, evaluate_cartpole_grid
from .collect import collect_episodes
from .finite import FiniteLinearMDP
from .hard_instance import HardInstance
from .policies import policy_table
from .put_option import EXERCISE, HOLD, AmericanPutOption
from .rollout_policies import EpsilonGreedy, UniformPolicy
from .simulated import SIMULATED_ACTIONS, SimulatedLinearMDP

__all__ = [
    "FiniteLinearMDP",
    "SimulatedLinearMDP",
    "SIMULATED_ACTIONS",
    "HardInstance",
    "AmericanPutOption",
    "HOLD",
    "EXERCISE",
    "Trajectories",
    "policy_table",
    "collect_episodes",
    "EpsilonGreedy",
    "UniformPolicy",
    "evaluate_cartpole_grid",
    "GridEvaluation",
]
