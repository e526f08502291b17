"""DRPVI (Liu & Xu, 2024): pessimistic value iteration for d-rectangular TV uncertainty balls."""

from __future__ import annotations

import numpy as np

from ..duals.constrained import tv_constrained
from ..duals.ranges import value_range
from ..engine import StepContext, StepRule
from ._params import check_flag, check_radius, check_v_min, floor_value, shared_docs
from ._variance import VarianceAwareMixin
from .base import LinearEstimator

__all__ = ["DRPVI", "TVBallRule", "step_value_range"]


def step_value_range(v: np.ndarray, ctx: StepContext) -> tuple[float, float]:
    """The known range of ``V_{h+1}``: ``[0, (H - h - 1) r_max]`` (the engine clips every
    learned ``Q_{h+1}`` to it), widened to hold known next-state values (``v``) outside it;
    :func:`r2pvi.duals.ranges.value_range` at the step's bound."""
    return value_range(v, ctx.next_value_bound)


class TVBallRule(StepRule):
    """TV ball (Liu & Xu 2024, eq. (4.4)): per factor, the exact maximum over all breakpoints
    ``alpha`` of ``[Lambda^-1 sum phi [V]_alpha]_i - rho_{h,i} (alpha - min_s V(s))``."""

    def __init__(self, rho, v_min):
        self.rho, self.v_min = rho, v_min  # rho: (H, d)

    def __call__(self, E, v, ctx):
        floor = floor_value(self.v_min, v)
        rho = self.rho[ctx.h] if ctx.dims is None else self.rho[ctx.h][ctx.dims]
        # PEVI's range: rho_{h,i} = 0 gives PEVI's projected estimate, the limit rho -> 0+
        # (a v_min below the range lowers only the results' lower end, tv_constrained)
        return tv_constrained(E, v, rho, floor, v_range=step_value_range(v, ctx))

    def factor_params(self, h):
        return self.rho[h]


@shared_docs
class DRPVI(VarianceAwareMixin, LinearEstimator):
    """Distributionally robust pessimistic value iteration with TV uncertainty balls.

    The d-DRMDP baseline of the paper (Liu & Xu 2024, eq. (4.4) and Algorithm 1):
    ``Q_h = clip(phi^T (theta_h + w_h) - Gamma_h(phi), 0, (H - h) r_max)`` where ``w_h,i``
    estimates ``inf {E_mu V_{h+1} : D_TV(mu || mu0_{h,i}) <= rho_{h,i}}`` through the dual
    ``max_{alpha} E_hat_i[V]_alpha - rho_{h,i} (alpha - min_s V(s))``, maximized exactly over
    every breakpoint (no Nelder-Mead; see :func:`~r2pvi.duals.tv_constrained`).

    Numerical guarantees (any data, also signed ridge weights): each ``w_h,i`` is finite and
    lies in ``[min(V_min, m), m]`` with ``m`` the plain ridge estimate of ``E_i V_{h+1}``
    clipped to ``[0, (H - h - 1) r_max]`` (the ball contains ``mu0``, so the robust value
    never exceeds it); it is non-increasing in ``rho``, ``rho_{h,i} = 0`` gives ``m``,
    :class:`~r2pvi.PEVI`'s projected estimate (the limit ``rho -> 0+``: continuous at 0), and
    any radius past saturation (``rho = 1e16``) gives ``V_min`` exactly. VA-DRPVI has the
    same guarantees on its weighted operator.

    Parameters
    ----------
    rho : float, array (d,) or array (H, d)
        Radii of the TV balls (>= 0; ``rho >= 1`` allows any distribution): one for all,
        one per factor, or one per step and factor (0-based steps). ``rho_{h,i} = 0`` uses
        PEVI's estimate for that factor (the plain ridge estimate projected onto the value
        range), so ``rho = 0`` is PEVI with the same ``beta``, ``gamma`` and ``penalty``.
    beta : float, default 1.0
        Scale of the pessimism penalty (>= 0).
    gamma : float, default 1.0
        Ridge parameter (> 0).
    penalty : {"l1", "l2", "elliptical"}, default "l1"
        Penalty form, as in :class:`~r2pvi.R2PVI` ("l1" is the d-rectangular form).
    v_min : "data" or float, default "data"
        Source of ``min_s V_{h+1}(s)``: the minimum over the sampled next-state values, or a
        known lower bound on the value (e.g. 0 when a zero-value fail state exists).
    reward_weights : array (H, d), optional
        Known ``theta_h``; None estimates them by ridge regression.
    r_max : float, default 1.0
        Reward bound: ``Q_h`` is clipped to ``[0, (H - h) r_max]``.
    variance_aware : bool, default False
        VA-DRPVI (Liu & Xu 2024): a first, unweighted DRPVI pass gives
        ``V_{h+1}``, whose estimated conditional variance (in units of ``r_max^2``, floored
        at 1; :func:`~r2pvi.algorithms._variance.variance_weights`) weights a second pass
        (weighted Gram matrix, targets and penalty).
    time_homogeneous : {"auto", True, False}, default "auto"
        {time_homogeneous}

    Attributes
    ----------
    weights_ : ndarray (H, d)
        ``theta_h + w_h`` for every 0-based step.
    reward_weights_ : ndarray (H, d)
    gram_inv_diag_ : ndarray (H, d)

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> from r2pvi.algorithms import DRPVI
    >>> rng = np.random.default_rng(0)
    >>> K, H, d, A = 200, 3, 4, 2
    >>> phi = rng.dirichlet(np.ones(d), size=(K, H))
    >>> next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    >>> ds = OfflineDataset.from_features(phi, phi @ np.linspace(0, 1, d), next_phi)
    >>> rho = np.zeros((H, d)); rho[0, 3] = 0.3       # perturb factor 4 at the first step
    >>> est = DRPVI(rho, beta=0.1).fit(ds)
    >>> est.weights_.shape, est.act(next_phi[:3, 0], h=1).shape
    ((3, 4), (3,))
    """

    def __init__(
        self,
        rho,
        *,
        beta=1.0,
        gamma=1.0,
        penalty="l1",
        v_min="data",
        reward_weights=None,
        r_max=1.0,
        variance_aware=False,
        time_homogeneous="auto",
    ):
        self.rho = rho
        self.beta = beta
        self.gamma = gamma
        self.penalty = penalty
        self.v_min = v_min
        self.reward_weights = reward_weights
        self.r_max = r_max
        self.variance_aware = variance_aware
        self.time_homogeneous = time_homogeneous

    def _validate_extra(self, dataset):
        return {
            "rho": check_radius(self.rho, dataset.horizon, dataset.n_features),
            "v_min": check_v_min(self.v_min),
            "variance_aware": check_flag(self.variance_aware, "variance_aware"),
        }

    def _make_rule(self, params):
        return TVBallRule(params["rho"], params["v_min"])
