"""R2PVI: robust regularized pessimistic value iteration (the paper's Algorithms 1 and 2)."""

from __future__ import annotations

import copy
import math

from .._validation import check_choice, check_scalar
from ..duals.fdivergence import FDivergence, get_divergence
from ..duals.general_f import f_regularized
from ..duals.ranges import project_onto_range, value_extent, value_range, value_unit
from ..duals.regularized import (
    KL_FORMS,
    MOMENTS,
    chi2_regularized,
    kl_regularized,
    tv_regularized,
)
from ..engine import StepRule
from ._params import check_flag, check_v_min, shared_docs
from ._variance import VarianceAwareMixin
from .base import LinearEstimator

THEORY = "theory"

__all__ = ["R2PVI", "TVRule", "KLRule", "Chi2Rule", "FDivergenceRule"]


def _step_range(v, ctx, v_min="data", extent=None, unit=1.0):
    """``[lower, upper]`` of ``V_{h+1}`` (:func:`~r2pvi.duals.ranges.value_range`): 0 (or a
    negative known ``v_min``) to the step's own bound ``(H - h - 1) r_max``. ``extent``:
    ``(min v, max v)`` if the rule has them; ``unit``: the unit ``v`` (and ``v_min``) are
    measured in (:func:`~r2pvi.duals.ranges.value_unit`)."""
    lower = 0.0 if v_min == "data" else min(0.0, float(v_min))
    return value_range(v, ctx.next_value_bound / unit, lower, extent=extent)


# lam below this many value units acts as it: 1 / lam stays finite (lam / unit would
# underflow to 0 for lam = 1e-300 and values of 1e300); far below any value's resolution.
_LAM_FLOOR = 2.0**-1000


def _in_units(v, v_min="data"):
    """``(unit, v / unit, v_min / unit, extent of v / unit)`` with ``unit =
    value_unit(extent of v)``, a power of two (exact): the values' own scale, so the formulas
    see values in ``[-2, 2]`` whatever the scale of the rewards and ``r_max``."""
    ext = value_extent(v)
    unit = value_unit(ext)
    if unit == 1.0:
        return unit, v, v_min, ext
    return (unit, v / unit, (v_min if v_min == "data" else v_min / unit),
            (ext[0] / unit, ext[1] / unit))


class TVRule(StepRule):
    """TV closed form (eq. TV-estimation): ridge regression of ``[V]_{V_min + lam}``."""

    def __init__(self, lam, v_min):
        self.lam, self.v_min = lam, v_min

    def __call__(self, E, v, ctx):
        ext = value_extent(v)  # once: the floor and the step's range
        w = tv_regularized(E, v, self.lam, ext[0] if self.v_min == "data" else self.v_min)
        return project_onto_range(w, *_step_range(v, ctx, self.v_min, ext))


class KLRule(StepRule):
    """KL (eq. KL-estimation): ``form="normalized"`` is ``s_i`` times the dual of the
    row-normalized ridge weights, capped at the step's bound; ``form="paper"`` is the literal
    ``-lam log max{w', exp(-H r_max / lam)}``; ``moments`` as in
    :func:`~r2pvi.duals.kl_regularized` (R2PVI passes "valid")."""

    def __init__(self, lam, form="normalized", moments="ridge"):
        self.lam, self.form, self.moments = lam, form, moments

    def __call__(self, E, v, ctx):
        ext = value_extent(v)  # once: the step's range and the dual's shift and spread
        lo, hi = _step_range(v, ctx, extent=ext)
        cap = hi if self.form == "normalized" else ctx.v_upper
        w = kl_regularized(E, v, self.lam, cap, self.form, extent=ext, moments=self.moments)
        return project_onto_range(w, lo, hi)


class Chi2Rule(StepRule):
    """chi^2 (eq. parameter estimation x2): exact maximization over alpha of the centered
    moments, clipped to the range of the centered values ``[0, (H - h - 1) r_max - min V]``;
    ``moments`` as in :func:`~r2pvi.duals.chi2_regularized` (R2PVI passes "valid")."""

    def __init__(self, lam, moments="ridge"):
        self.lam, self.moments = lam, moments

    def __call__(self, E, v, ctx):
        # in the values' unit (value_unit): their squares stay finite and normal; the extent
        # once: the step's range, the centering and the dual's range
        unit, u, _, ext = _in_units(v)
        lo, hi = _step_range(u, ctx, extent=ext, unit=unit)
        top = hi - ext[0]
        lam = max(self.lam / unit, _LAM_FLOOR)
        w = chi2_regularized(E, u, lam, (0.0, top), (0.0, top * top), extent=ext,
                             moments=self.moments)
        w = project_onto_range(w, lo, hi)
        return w if unit == 1.0 else w * unit


class FDivergenceRule(StepRule):
    """General f (Algorithm 1): ``sup_alpha E_hat[alpha - lam f*((alpha - V)/lam)]``."""

    def __init__(self, lam, divergence, v_min):
        self.lam, self.divergence, self.v_min = lam, divergence, v_min

    def __call__(self, E, v, ctx):
        # in the values' unit (value_unit): the search's tolerances are relative to 1
        unit, u, v_min, ext = _in_units(v, self.v_min)
        lam = max(self.lam / unit, _LAM_FLOOR)
        w = f_regularized(E, u, lam, self.divergence, ext[0] if v_min == "data" else v_min)
        w = project_onto_range(w, *_step_range(u, ctx, v_min, ext, unit))
        return w if unit == 1.0 else w * unit


_CLOSED_FORMS = {"tv", "kl", "chi2"}


@shared_docs
class R2PVI(VarianceAwareMixin, LinearEstimator):
    """Robust regularized pessimistic value iteration (the paper's R2PVI).

    ``Q_h = clip(phi^T (theta_h + w_h) - Gamma_h(phi), 0, (H - h) r_max)`` where ``w_h,i``
    estimates ``inf_mu E_mu V_{h+1} + lam D(mu || mu0_{h,i})`` through the divergence's dual.

    Parameters
    ----------
    divergence : {"tv", "kl", "chi2", "hellinger"} or FDivergence, default "tv"
        "tv", "kl" and "chi2" use the paper's closed-form / exact estimators; "hellinger" and
        any :class:`~r2pvi.FDivergence` object (built-ins included) use the general dual of
        Algorithm 1 with a bracketed 1-D solver per dimension.
    lam : float, default 1.0
        Regularization strength ``lambda > 0``; smaller is more robust.
    beta : float or "theory", default 1.0
        Scale of the pessimism penalty (>= 0). ``"theory"`` takes the beta of the paper's
        instance-dependent upper-bound theorem for the dataset's d, H and K and ``delta``
        (:func:`r2pvi.theory.theoretical_beta`), so that with probability at least
        ``1 - delta`` ``SubOpt <= 2 beta * (uncertainty term)``
        (:func:`r2pvi.theory.uncertainty_term`). The theorem covers the closed forms
        "tv", "kl" and "chi2" with its own setting: ``gamma = 1``, the "l1" penalty,
        rewards in ``[0, 1]`` (``r_max = 1``) and no variance weighting; anything else
        raises ``ValueError`` at ``fit``. This beta is very large (hundreds to millions):
        the learned policy is then extremely pessimistic.
    gamma : float, default 1.0
        Ridge parameter (> 0).
    penalty : {"l1", "l2", "elliptical"}, default "l1"
        "l1" is the paper's d-rectangular ``beta sum_i |phi_i| sqrt([Lambda^-1]_ii)``;
        "l2" the authors' code's ``beta sqrt(sum_i phi_i^2 [Lambda^-1]_ii)``; "elliptical"
        is PEVI's (non-robust) bonus ``beta ||phi||_{Lambda^-1} = beta sqrt(phi^T
        Lambda^-1 phi)``, the norm of ``phi`` in the ellipsoid of the inverse Gram matrix
        (it uses the off-diagonal entries too; for comparisons with PEVI).
    v_min : "data" or float, default "data"
        Source of ``min_s V_{h+1}(s)`` used by TV (``alpha = V_min + lam``) and by
        divergences that can move mass off the nominal support: "data" takes the minimum
        over the sampled next-state values (as the authors' code does); a float is a known
        lower bound on the value (e.g. 0 when a zero-value fail state exists).
    reward_weights : array (H, d), optional
        Known ``theta_h`` (the paper assumes them known); None estimates them by ridge.
    r_max : float, default 1.0
        Reward bound. ``Q_h`` is clipped to ``[0, (H - h) r_max]``, and every factor value
        ``w_{h,i}`` to the range of ``V_{h+1}``, ``[0, (H - h - 1) r_max]``
        (:mod:`r2pvi.duals.ranges`); chi^2 clips the moments of the centered values
        ``V - min V`` to that range.
    variance_aware : bool, default False
        VA-R2PVI-TV (TV only): a first, unweighted pass gives ``V_{h+1}``, whose conditional
        variance ``sigma_h^2 = max{1, [phi^T z2]_[0,H^2] - ([phi^T z1]_[0,H])^2}``, in units
        of ``r_max`` (``z1``, ``z2`` the ridge estimates of ``V / r_max`` and its square: the
        paper's formula, whose rewards lie in ``[0, 1]``), weights a second pass (weighted
        Gram matrix, targets and penalty); see
        :func:`~r2pvi.algorithms._variance.variance_weights`.
    delta : float in (0, 1), default 0.05
        Confidence of ``beta="theory"`` (the theorem's bound holds with probability at least
        ``1 - delta``); unused otherwise.
    kl_form : {"normalized", "paper"}, default "normalized"
        KL only. "normalized": ``w_i = s_i (c - lam log(E_i[exp(-(V - c)/lam)] / s_i))`` with
        ``s_i`` the sum of the factor's ridge weights and ``c = min V``: the exact dual for
        true expectations, the plain ridge estimate as ``lam -> inf`` and ``s_i`` times the
        factor's smallest sampled value as ``lam -> 0``. "paper": the literal
        ``-lam log max{w', exp(-H r_max/lam)}``, whose ridge shrinkage bias ``-lam log s_i``
        grows with ``lam``. See :func:`~r2pvi.duals.kl_regularized`.
    time_homogeneous : {"auto", True, False}, default "auto"
        {time_homogeneous}
    moments : {"valid", "ridge"}, default "valid"
        KL (``kl_form="normalized"``) and chi^2 only: how a factor's moments are estimated
        from its signed ridge weights ``M_i`` (row sum ``s_i``). "valid": the normalized
        weights ``M_i / s_i`` are taken to hold at least ``f_i = 1 / (1 + N_i)`` of their
        mass at the least value ``c``, with ``N_i = s_i^2 / [Lambda^-1]_ii`` the factor's
        effective count: KL's normalized moment is kept in ``[max(f_i, e^{-(max V -
        c)/lam}), 1]`` (so ``w_i <= s_i (c + lam log(1 + N_i))``), chi^2 is ``s_i`` times the
        dual of ``M_i / s_i``, at most ``s_i (c + lam N_i)``. "ridge": the moments as
        regressed (a KL moment <= 0 gives the plain estimate ``E_i V``; chi^2 uses ``M_i``
        unnormalized), the estimator before this option. Exact distributions are unchanged
        either way. See the user guide's page on rare events.

    Attributes
    ----------
    weights_ : ndarray (H, d)
        ``theta_h + w_h`` for every 0-based step.
    reward_weights_ : ndarray (H, d)
    gram_inv_diag_ : ndarray (H, d)
        ``diag(Lambda_h^{-1})`` (the d-rectangular penalty's ingredients).
    beta_ : float
        The penalty scale used: ``beta``, or the theorem's value for ``beta="theory"``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset, R2PVI
    >>> rng = np.random.default_rng(0)
    >>> K, H, d, A = 200, 3, 4, 2
    >>> phi = rng.dirichlet(np.ones(d), size=(K, H))
    >>> next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    >>> ds = OfflineDataset.from_features(phi, phi @ np.linspace(0, 1, d), next_phi)
    >>> est = R2PVI("kl", lam=0.5, beta=0.1).fit(ds)
    >>> est.weights_.shape, est.act(next_phi[:3, 0], h=1).shape
    ((3, 4), (3,))
    >>> round(R2PVI("tv", lam=0.5, beta="theory").fit(ds).beta_, 1)  # 16 H d sqrt(xi_TV)
    1282.7
    """

    def __init__(
        self,
        divergence="tv",
        lam=1.0,
        *,
        beta=1.0,
        gamma=1.0,
        penalty="l1",
        v_min="data",
        reward_weights=None,
        r_max=1.0,
        variance_aware=False,
        delta=0.05,
        kl_form="normalized",
        time_homogeneous="auto",
        moments="valid",
    ):
        self.divergence = divergence
        self.lam = lam
        self.beta = beta
        self.gamma = gamma
        self.penalty = penalty
        self.v_min = v_min
        self.reward_weights = reward_weights
        self.r_max = r_max
        self.variance_aware = variance_aware
        self.delta = delta
        self.kl_form = kl_form
        self.time_homogeneous = time_homogeneous
        self.moments = moments

    def _validate_common(self, dataset):
        beta = self.beta
        if isinstance(beta, str):
            if beta.lower() != THEORY:
                raise ValueError(f"beta must be a number >= 0 or 'theory', got {beta!r}")
            # Validate the other shared parameters as usual; _validate_extra sets beta.
            shadow = copy.copy(self)
            shadow.beta = 0.0
            return super(R2PVI, shadow)._validate_common(dataset)
        return super()._validate_common(dataset)

    def _validate_extra(self, dataset):
        lam = check_scalar(self.lam, "lam", low=0.0, low_inclusive=False)
        v_min = check_v_min(self.v_min)
        variance_aware = check_flag(self.variance_aware, "variance_aware")
        div = self.divergence
        if isinstance(div, str) and div.lower() in _CLOSED_FORMS:
            div = div.lower()
        elif isinstance(div, str | FDivergence):
            div = get_divergence(div)
        else:
            raise TypeError(
                "divergence must be 'tv', 'kl', 'chi2', 'hellinger' or an FDivergence, got "
                f"{div!r}"
            )
        is_tv = div == "tv" if isinstance(div, str) else div.name == "tv"
        if variance_aware and not is_tv:
            raise ValueError(
                "variance_aware=True is only defined for divergence='tv' (VA-R2PVI-TV), got "
                f"divergence={self.divergence!r}; use variance_aware=False"
            )
        delta = check_scalar(self.delta, "delta", low=0.0, high=1.0, low_inclusive=False)
        if delta >= 1.0:
            raise ValueError(f"delta must lie in (0, 1), got {delta}")
        kl_form = check_choice(self.kl_form, "kl_form", KL_FORMS)
        moments = check_choice(self.moments, "moments", MOMENTS)
        extra = {"lam": lam, "v_min": v_min, "divergence": div,
                 "variance_aware": variance_aware, "kl_form": kl_form, "moments": moments}
        if isinstance(self.beta, str):
            extra["beta"] = self._theory_beta(dataset, div, lam, delta, variance_aware)
        return extra

    def _theory_beta(self, dataset, div, lam, delta, variance_aware) -> float:
        """beta of the instance-dependent upper-bound theorem, after checking its setting."""
        from ..theory.bounds import theoretical_beta

        if not (isinstance(div, str) and div in _CLOSED_FORMS):
            raise ValueError(
                "beta='theory' is the theorem's beta for divergence 'tv', 'kl' or 'chi2' "
                f"(closed forms), got divergence={self.divergence!r}; pass a numeric beta"
            )
        gamma, r_max = float(self.gamma), float(self.r_max)
        problems = [
            text for bad, text in (
                (variance_aware, "variance_aware=False"),
                (str(self.penalty).lower() != "l1", "penalty='l1'"),
                (gamma != 1.0, "gamma=1"),
                (r_max != 1.0, "r_max=1 (rewards in [0, 1])"),
            ) if bad
        ]
        if problems:
            raise ValueError(
                "beta='theory' is only defined in the theorem's setting; it needs "
                + ", ".join(problems) + "; pass a numeric beta otherwise"
            )
        beta = theoretical_beta(div, dataset.n_features, dataset.horizon,
                                dataset.n_trajectories, lam, delta)
        if not math.isfinite(beta):
            raise ValueError(
                f"the theoretical beta of R2PVI-KL overflows for lam = {lam} (it grows like "
                f"e^(H/lam), H = {dataset.horizon}); use a larger lam or a numeric beta"
            )
        return beta

    def _set_fitted(self, model, params, n_actions):
        super()._set_fitted(model, params, n_actions)
        self.beta_ = float(params["beta"])

    def _make_rule(self, params):
        div, lam, v_min = params["divergence"], params["lam"], params["v_min"]
        if div == "tv":
            return TVRule(lam, v_min)
        if div == "kl":
            return KLRule(lam, params["kl_form"], params["moments"])
        if div == "chi2":
            return Chi2Rule(lam, params["moments"])
        return FDivergenceRule(lam, div, v_min)
