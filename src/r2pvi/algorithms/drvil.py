"""DRVI-L (Ma et al., 2022): pessimistic value iteration for d-rectangular KL uncertainty balls."""

from __future__ import annotations

from ..duals.constrained import kl_constrained
from ..engine import StepRule
from ._params import check_radius
from .base import LinearEstimator

__all__ = ["DRVIL", "KLBallRule"]


class KLBallRule(StepRule):
    """KL ball (Ma et al. 2022, DRVI-L): per factor, ``sup_{b>0} -b log(1 + clip(
    [Lambda^-1 sum phi (e^{-V/b} - 1)]_i, e^{-H/b} - 1, 0)) - b rho_{h,i}``."""

    def __init__(self, rho):
        self.rho = rho  # (H, d)

    def __call__(self, E, v, ctx):
        rho = self.rho[ctx.h] if ctx.dims is None else self.rho[ctx.h][ctx.dims]
        return kl_constrained(E, v, rho, v_max=ctx.v_upper, centered=True)

    def factor_params(self, h):
        return self.rho[h]


class DRVIL(LinearEstimator):
    """Distributionally robust value iteration with KL uncertainty balls (DRVI-L).

    The d-DRMDP KL baseline of the paper (Ma et al. 2022): ``Q_h = clip(phi^T (theta_h +
    w_h) - Gamma_h(phi), 0, (H - h) r_max)`` where ``w_h,i`` estimates
    ``inf {E_mu V_{h+1} : D_KL(mu || mu0_{h,i}) <= rho_{h,i}}`` through the dual
    ``sup_{b>0} -b log E_i[e^{-V/b}] - b rho_{h,i}``. As in Ma et al., the ridge regression
    estimates ``E_i[e^{-V/b}] - 1`` (regressing ``e^{-V/b} - 1``, so the estimate shrinks
    towards 1), clipped to ``[e^{-H r_max/b} - 1, 0]`` so that its log is defined; the 1-D
    problem in ``b`` is solved to machine precision for all factors at once
    (see :func:`~r2pvi.duals.kl_constrained` with ``centered=True``).

    Parameters
    ----------
    rho : float, array (d,) or array (H, d)
        Radii of the KL balls (>= 0): one for all, one per factor, or one per step and factor.
        ``rho_{h,i} = 0`` uses the plain ridge estimate for that factor.
    beta : float, default 1.0
        Scale of the pessimism penalty (>= 0).
    gamma : float, default 1.0
        Ridge parameter (> 0).
    penalty : {"l1", "l2", "elliptical"}, default "l1"
        Penalty form, as in :class:`~r2pvi.R2PVI`.
    reward_weights : array (H, d), optional
        Known ``theta_h``; None estimates them by ridge regression.
    r_max : float, default 1.0
        Reward bound: ``Q_h`` is clipped to ``[0, (H - h) r_max]``; the estimate of
        ``E[e^{-V/b}]`` is floored at ``e^{-H r_max / b}``.
    time_homogeneous : bool, default False
        Pooled steps: every step's regressions use the transitions of all H steps, with one
        Gram matrix factored once (per-step work: next-state values and regressions). Valid
        only when the nominal dynamics and rewards do not depend on h (a time-homogeneous MDP,
        e.g. a Gymnasium environment); False is the paper's per-step estimator.

    Attributes
    ----------
    weights_ : ndarray (H, d)
    reward_weights_ : ndarray (H, d)
    gram_inv_diag_ : ndarray (H, d)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> from r2pvi.algorithms import DRVIL
    >>> rng = np.random.default_rng(0)
    >>> K, H, d, A = 200, 3, 4, 2
    >>> phi = rng.dirichlet(np.ones(d), size=(K, H))
    >>> next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    >>> ds = OfflineDataset.from_features(phi, phi @ np.linspace(0, 1, d), next_phi)
    >>> est = DRVIL(0.1, beta=0.1).fit(ds)
    >>> est.weights_.shape, est.act(next_phi[:3, 0], h=1).shape
    ((3, 4), (3,))
    """

    def __init__(self, rho, *, beta=1.0, gamma=1.0, penalty="l1", reward_weights=None,
                 r_max=1.0, time_homogeneous=False):
        self.rho = rho
        self.beta = beta
        self.gamma = gamma
        self.penalty = penalty
        self.reward_weights = reward_weights
        self.r_max = r_max
        self.time_homogeneous = time_homogeneous

    def _validate_extra(self, dataset):
        return {"rho": check_radius(self.rho, dataset.horizon, dataset.n_features)}

    def _make_rule(self, params):
        return KLBallRule(params["rho"])
