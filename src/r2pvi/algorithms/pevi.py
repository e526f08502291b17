"""PEVI (Jin et al., 2021): non-robust pessimistic value iteration."""

from __future__ import annotations

from ..duals.ranges import project_onto_range, value_range
from ..engine import StepRule
from ._params import shared_docs
from .base import LinearEstimator

__all__ = ["PEVI", "RidgeRule"]


class RidgeRule(StepRule):
    """Non-robust: ``w_h = Lambda_h^{-1} sum_tau phi_tau V_{h+1}(s'_tau)``, each factor kept in
    the range of ``V_{h+1}``, ``[0, (H - h - 1) r_max]`` (:mod:`r2pvi.duals.ranges`)."""

    def __call__(self, E, v, ctx):
        return project_onto_range(E(v), *value_range(v, ctx.next_value_bound))


@shared_docs
class PEVI(LinearEstimator):
    """Pessimistic value iteration with linear function approximation (non-robust baseline).

    ``Q_h = clip(phi^T (theta_h + w_h) - beta ||phi||_{Lambda_h^{-1}}, 0, (H - h) r_max)``
    with ``w_h`` the ridge regression of the next-step values.

    Parameters
    ----------
    beta : float, default 1.0
        Scale of the pessimism penalty (>= 0).
    gamma : float, default 1.0
        Ridge parameter of the Gram matrix (> 0).
    reward_weights : array (H, d), optional
        Known reward parameters ``theta_h``; None estimates them by ridge regression.
    r_max : float, default 1.0
        Reward bound: ``Q_h`` is clipped to ``[0, (H - h) r_max]`` (0-based ``h``).
    penalty : {"elliptical", "l1", "l2"}, default "elliptical"
        Penalty form (PEVI's own is the elliptical norm).
    time_homogeneous : {"auto", True, False}, default "auto"
        {time_homogeneous}

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset, PEVI
    >>> rng = np.random.default_rng(0)
    >>> phi = rng.dirichlet(np.ones(3), size=(50, 2))
    >>> ds = OfflineDataset.from_features(phi, phi[..., 0], rng.dirichlet(np.ones(3), (50, 2, 2)))
    >>> est = PEVI(beta=0.1).fit(ds)
    >>> est.weights_.shape
    (2, 3)
    """

    def __init__(self, *, beta=1.0, gamma=1.0, reward_weights=None, r_max=1.0,
                 penalty="elliptical", time_homogeneous="auto"):
        self.beta = beta
        self.gamma = gamma
        self.reward_weights = reward_weights
        self.r_max = r_max
        self.penalty = penalty
        self.time_homogeneous = time_homogeneous

    def _make_rule(self, params):
        return RidgeRule()
