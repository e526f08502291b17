"""Theory in practice: the paper's beta, bounds and the instance-dependent uncertainty term.

- :func:`theoretical_beta`, :func:`xi`: the beta of Thm. instance-dependent upper bounds
  (``R2PVI(beta="theory")`` uses it);
- :func:`uncertainty_term` (and :func:`uncertainty_values`): the term
  ``sup_{P in U^lam(P0)} sum_h E^{pi*,P}[sum_i ||phi_i 1_i||_{Lambda_h^{-1}}]`` of the upper
  and lower bounds, exactly, on a finite linear MDP;
- :func:`instance_dependent_bound` (``2 beta * term``) and
  :func:`instance_independent_bound` (the corollary under partial coverage);
- :func:`loglog_slope`: the empirical rate of SubOpt in K with a bootstrap interval.
"""

from .bounds import instance_dependent_bound, instance_independent_bound, theoretical_beta, xi
from .rates import SlopeFit, loglog_slope
from .uncertainty import (
    admissible_radii,
    ball_sup,
    bonus_table,
    uncertainty_term,
    uncertainty_values,
)

__all__ = [
    "theoretical_beta",
    "xi",
    "instance_dependent_bound",
    "instance_independent_bound",
    "admissible_radii",
    "ball_sup",
    "bonus_table",
    "uncertainty_values",
    "uncertainty_term",
    "SlopeFit",
    "loglog_slope",
]
