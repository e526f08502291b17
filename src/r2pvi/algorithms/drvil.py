"""DRVI-L (Ma et al., 2022): pessimistic value iteration for d-rectangular KL uncertainty balls."""

from __future__ import annotations

import math
import numbers

import numpy as np

from .._validation import check_choice
from ..duals.constrained import kl_constrained
from ..duals.ranges import value_extent, value_range, value_unit
from ..engine import StepContext, StepRule
from ._params import check_radius, shared_docs
from .base import LinearEstimator

__all__ = ["DRVIL", "KLBallRule", "auto_b_min"]


def auto_b_min(v: np.ndarray, n_samples: int) -> float | None:
    """``b_min="auto"``: ``(max v - min v) / log K`` (None when every value is the same).

    From K samples the ridge estimate of ``E[e^{-V/b}]`` cannot resolve probabilities below
    about ``1/K``; below this ``b`` the tilt ``e^{-V/b}`` weighs the lowest sampled value more
    than K times the highest, and the estimated objective is decided by the estimate's error
    (negative ridge weights, the ``gamma`` shrinkage), not by the data: Ma et al.'s error
    bound grows as ``e^{H / underline beta} / sqrt(K)``.

    Examples
    --------
    >>> round(auto_b_min(np.array([0.0, 0.5, 2.0]), 1000), 6)
    0.28953
    """
    spread = float(np.max(v) - np.min(v))
    if not spread > 0:
        return None
    return spread / math.log(max(int(n_samples), 3))


DRVIL_FORMS = ("normalized", "ma")


class KLBallRule(StepRule):
    """KL ball (DRVI-L): per factor, ``sup_{b >= b_min} -b log u_i(b) - b rho_{h,i}`` with
    ``u_i(b)`` the ridge estimate of ``E_i[e^{-V/b}]``, floored at ``e^{-m_i/b}``, ``m_i`` the
    plain ridge estimate clipped to the step's value range. ``form="normalized"``: ``s_i``
    times the dual under the row-normalized weights (``s_i = [Lambda^-1 sum phi]_i``);
    ``form="ma"``: Ma et al. 2022's ``u_i = 1 + clip([Lambda^-1 sum phi (e^{-V/b} - 1)]_i,
    e^{-m_i/b} - 1, 0)`` (see :func:`~r2pvi.duals.kl_constrained`)."""

    def __init__(self, rho, b_min="auto", form="normalized"):
        self.rho = rho  # (H, d)
        self.b_min = b_min  # "auto", a positive float or None
        self.form = form

    def __call__(self, E, v, ctx: StepContext):
        # in the values' unit (value_unit, a power of two: exact): the search over b has
        # tolerances relative to 1 and squares b
        unit = value_unit(value_extent(v))
        u = v if unit == 1.0 else v / unit
        if self.b_min == "auto":
            b_min = auto_b_min(u, E.n_points)
        else:
            # (a b_min below 2^-1000 value units acts as that: 1 / b stays finite)
            b_min = None if self.b_min is None else max(self.b_min / unit, 2.0**-1000)
        rho = self.rho[ctx.h] if ctx.dims is None else self.rho[ctx.h][ctx.dims]
        ma = self.form == "ma"
        w = kl_constrained(E, u, rho, v_range=value_range(u, ctx.next_value_bound / unit),
                           centered=ma, normalized=not ma, b_min=b_min)
        return w if unit == 1.0 else w * unit

    def factor_params(self, h):
        return self.rho[h]


def check_b_min(b_min):
    """Validate ``b_min``: "auto", None or a finite positive number."""
    if isinstance(b_min, str):
        if b_min.lower() != "auto":
            raise ValueError(f"b_min must be 'auto', None or a positive number, got {b_min!r}")
        return "auto"
    if b_min is None:
        return None
    if isinstance(b_min, bool) or not isinstance(b_min, numbers.Real):
        raise TypeError(f"b_min must be 'auto', None or a positive number, got {b_min!r}")
    b = float(b_min)
    if not (np.isfinite(b) and 0 < b <= B_MIN_MAX):
        raise ValueError(
            f"b_min must be a number in (0, {B_MIN_MAX:g}] (or 'auto', or None to search "
            f"b -> 0), got {b_min!r}; the dual's b is searched from b_min up on a log grid, "
            "and beyond the values' range over rho every larger b_min gives the same fit"
        )
    return b


# Largest b_min accepted: the search's grid of b reaches a few times b_min, which must stay
# finite in float64.
B_MIN_MAX = 1e300


@shared_docs
class DRVIL(LinearEstimator):
    """Distributionally robust value iteration with KL uncertainty balls (DRVI-L).

    The d-DRMDP KL baseline of the paper (Ma et al. 2022): ``Q_h = clip(phi^T (theta_h +
    w_h) - Gamma_h(phi), 0, (H - h) r_max)`` where ``w_h,i`` estimates
    ``inf {E_mu V_{h+1} : D_KL(mu || mu0_{h,i}) <= rho_{h,i}}`` through the dual
    ``sup_{b >= b_min} -b log E_i[e^{-V/b}] - b rho_{h,i}``. By default (``form="normalized"``)
    each factor is ``s_i`` times that dual under its row-normalized ridge weights (``s_i`` their
    sum, below 1 by the ridge shrinkage), as R2PVI-KL's default form; ``form="ma"`` is Ma et
    al.'s estimate, the regression of ``e^{-V/b} - 1`` (the estimate shrinks towards 1, i.e. the
    leftover weight ``1 - s_i`` sits at ``V = 0``, which biases the result downwards, below every
    value, where V is far from 0). The 1-D problem in ``b`` is solved to machine precision for
    all factors at once (see :func:`~r2pvi.duals.kl_constrained`).

    Numerical guarantees (any data, also signed ridge weights): each ``w_h,i`` is finite and
    lies in ``[0, m]``, ``m`` the plain ridge estimate of ``E_i V_{h+1}`` clipped to
    ``[0, (H - h - 1) r_max]`` (the ball contains ``mu0``, so the robust value never exceeds
    it; the estimate of ``E_i[e^{-V/b}]`` is floored at ``e^{-m/b}``, Jensen's bound, instead
    of Ma et al.'s ``e^{-H/b}``); it is non-increasing in ``rho``, ``rho_{h,i} = 0`` gives
    ``m``, :class:`~r2pvi.PEVI`'s projected estimate (the limit ``rho -> 0+``: continuous at
    0), and a radius so large that no ``b >= b_min``
    gives a value above 0 (``rho = 1e10``) gives 0, the least value.

    Parameters
    ----------
    rho : float, array (d,) or array (H, d)
        Radii of the KL balls (>= 0): one for all, one per factor, or one per step and factor.
        ``rho_{h,i} = 0`` uses PEVI's estimate for that factor (the plain ridge estimate
        projected onto the value range): ``rho = 0`` is PEVI with the same ``beta``,
        ``gamma`` and ``penalty``.
    beta : float, default 1.0
        Scale of the pessimism penalty (>= 0).
    gamma : float, default 1.0
        Ridge parameter (> 0).
    penalty : {"l1", "l2", "elliptical"}, default "l1"
        Penalty form, as in :class:`~r2pvi.R2PVI`.
    reward_weights : array (H, d), optional
        Known ``theta_h``; None estimates them by ridge regression.
    r_max : float, default 1.0
        Reward bound: ``Q_h`` is clipped to ``[0, (H - h) r_max]``.
    b_min : "auto", float or None, default "auto"
        Lower end of the search over the dual variable ``b`` (Ma et al.'s regularity
        assumption: the optimal ``b`` is at least ``underline beta > 0``), in the units of
        the values. ``"auto"`` takes ``(max V - min V) / log K`` at every step (K samples;
        :func:`auto_b_min`): from K samples the ridge estimate of ``E[e^{-V/b}]`` cannot
        resolve probabilities below about ``1/K``, and at smaller ``b`` the estimated
        objective is decided by the estimate's error. Without it, a factor with (almost) no
        mass on the lowest values can get its plain estimate instead of a robust one (the
        ridge estimate of ``E[e^{-V/b}]`` crosses 0 as ``b -> 0``). None searches
        ``b -> 0`` (Ma et al.'s estimator without the assumption). A float must lie in
        ``(0, 1e300]`` (``B_MIN_MAX``).
    form : {"normalized", "ma"}, default "normalized"
        How the ridge regression estimates ``E_i[e^{-V/b}]``: ``s_i`` times the estimate
        under the row-normalized weights (no ridge shrinkage bias), or Ma et al.'s regression
        of ``e^{-V/b} - 1`` (:func:`~r2pvi.duals.kl_constrained`, ``normalized=`` /
        ``centered=``). The same for distributions.
    time_homogeneous : {"auto", True, False}, default "auto"
        {time_homogeneous}

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
                 r_max=1.0, b_min="auto", form="normalized", time_homogeneous="auto"):
        self.rho = rho
        self.beta = beta
        self.gamma = gamma
        self.penalty = penalty
        self.reward_weights = reward_weights
        self.r_max = r_max
        self.b_min = b_min
        self.form = form
        self.time_homogeneous = time_homogeneous

    def _validate_extra(self, dataset):
        return {"rho": check_radius(self.rho, dataset.horizon, dataset.n_features),
                "b_min": check_b_min(self.b_min),
                "form": check_choice(self.form, "form", DRVIL_FORMS)}

    def _make_rule(self, params):
        return KLBallRule(params["rho"], params["b_min"], params["form"])
