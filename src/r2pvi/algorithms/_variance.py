"""Variance-aware variants (VA-DRPVI, VA-R2PVI-TV): a second, variance-weighted pass.

Liu & Xu (2024), variance-aware DRPVI (VA-DRPVI), and the paper's VA-R2PVI-TV: a first pass of the
unweighted estimator gives ``V_{h+1}``; the conditional variance of ``V_{h+1}`` is estimated
by ridge regression of ``V`` and ``V^2`` under the first pass's Gram matrix; the second pass
re-runs the same engine with regression weights ``1 / sigma_h^2`` (weighted Gram matrix,
weighted targets, penalty with the weighted Gram matrix).
"""

from __future__ import annotations

import numpy as np

from ..data import OfflineDataset
from ..data.storage.sparse_rows import stack_rows
from ..engine import FittedModel, pooled_steps

__all__ = ["VarianceAwareMixin", "variance_weights"]


def variance_weights(dataset: OfflineDataset, first: FittedModel, v_upper: float) -> np.ndarray:
    """Regression weights ``1 / sigma_h^2(s_h^tau, a_h^tau)``, shape (H, K).

    ``sigma_h^2 = max{1, [phi^T z2]_{[0, v_upper^2]} - ([phi^T z1]_{[0, v_upper]})^2}``
    (Liu & Xu 2024, variance estimator of VA-DRPVI), in units of ``r_max``: ``z1``, ``z2``
    are the ridge estimates of ``U = V_{h+1} / r_max`` and ``U^2`` under the first pass's
    Gram matrix ``Lambda_h`` (``FittedModel.value_moments``) and ``v_upper = H`` the value
    bound in those units (the paper's ``H``, rewards in ``[0, 1]``). So the weights are
    dimensionless: scaling the rewards and ``r_max`` leaves them unchanged, and they are
    finite for any finite ``r_max`` (the squares of the values themselves overflow from
    ``r_max`` ~ 1e154 on). At ``r_max = 1`` this is the formula in the values' own units.
    At ``h = H-1``, ``V_H = 0`` and ``sigma^2 = 1``.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset
    >>> from r2pvi.algorithms import RidgeRule
    >>> from r2pvi.engine import backward_induction
    >>> rng = np.random.default_rng(0)
    >>> phi = rng.dirichlet(np.ones(3), size=(40, 4))
    >>> ds = OfflineDataset.from_features(phi, phi[..., 0], rng.dirichlet(np.ones(3), (40, 4, 2)))
    >>> first = backward_induction(ds, RidgeRule(), beta=0.0, gamma=1.0, penalty="l1", r_max=1.0,
    ...                            value_moments=True)
    >>> w = variance_weights(ds, first, v_upper=4.0)  # H = 4 (in units of r_max)
    >>> w.shape, bool(np.all((w > 0) & (w <= 1))), bool(np.all(w[-1] == 1))
    ((4, 40), True, True)
    """
    if first.value_moments is None:
        raise ValueError("variance_weights needs the first pass's value moments: run "
                         "backward_induction(..., value_moments=True)")
    H, K = dataset.horizon, dataset.n_trajectories
    n = first.next_state_values.shape[1]  # K, or P K for pooled steps (time_homogeneous)
    weights = np.ones((H, n))
    P = pooled_steps(H)  # pooled rows: steps 0 .. P-1 (P = 1: step 0's rows, as per step)
    pooled = stack_rows([dataset.step(h)[0] for h in range(P)]) if n != K else None
    for h in range(H - 1):  # V_H = 0: sigma_{H-1}^2 = max(1, 0) = 1
        z = first.value_moments[h]  # (d, 2): ridge estimates of U and U^2, U = V_{h+1}/r_max
        pred = np.asarray(dataset.step_times(h, z) if pooled is None else pooled @ z)
        mean = np.clip(pred[:, 0], 0.0, v_upper)
        second = np.clip(pred[:, 1], 0.0, v_upper * v_upper)
        weights[h] = 1.0 / np.maximum(1.0, second - mean * mean)
    return weights


class VarianceAwareMixin:
    """Adds the variance-aware second pass to an estimator with a ``variance_aware`` flag.

    Put it before :class:`~r2pvi.algorithms.LinearEstimator` in the bases; the validated
    parameters must contain ``"variance_aware"``. Subclasses (and tests) may override
    :meth:`_sample_weights`.
    """

    def _sample_weights(self, dataset: OfflineDataset, first: FittedModel, params: dict):
        return variance_weights(dataset, first, float(dataset.horizon))  # units of r_max

    def _fit_model(self, dataset: OfflineDataset, params: dict) -> FittedModel:
        if not params.get("variance_aware", False):
            return self._run_engine(dataset, params)
        first = self._run_engine(dataset, params, value_moments=True)
        weights = self._sample_weights(dataset, first, params)
        if np.all(weights == 1.0):  # sigma^2 = 1 everywhere: the second pass is the first
            return first
        return self._run_engine(dataset, params, sample_weights=weights)
