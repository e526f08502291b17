"""The one backward-induction engine shared by every algorithm (Algorithms 1-2 of the paper).

**Steps are 0-based in code**: the paper's step ``h = 1..H`` is ``h = 0..H-1`` here, so the
paper's clipping ``min{., H - h + 1}^+`` reads ``clip(., 0, (H - h) * r_max)``.

For ``h = H-1, ..., 0`` the engine

1. forms the Gram matrix ``Lambda_h = sum_tau w_tau phi_tau phi_tau^T + gamma I`` through its
   Cholesky factor (no explicit inverse);
2. computes the next-step values ``V_{h+1}(s') = max_a Q_{h+1}(s', a)`` at the sampled next
   states, taking known action values where the dataset gives them (``V_H = 0``);
3. asks the algorithm's :class:`StepRule` for the weights ``w_h`` — the only thing that
   differs between algorithms; at ``h = H-1`` the next values are identically 0 and
   ``w_{H-1} = 0`` for every divergence, so the rule is not called;
4. stores ``theta_h + w_h`` and what the penalty ``Gamma_h`` needs, which define
   ``Q_h = clip(phi^T (theta_h + w_h) - Gamma_h(phi), 0, (H - h) r_max)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .data import OfflineDataset
from .duals._scratch import release
from .duals.operators import RidgeExpectation, cholesky_gram

__all__ = [
    "StepRule",
    "StepContext",
    "FittedModel",
    "backward_induction",
    "penalty_values",
    "q_values_from_model",
    "PENALTIES",
]

PENALTIES = ("l1", "l2", "elliptical")


@dataclass(frozen=True)
class StepContext:
    """What a step rule may need besides the operator and the values."""

    h: int  # 0-based step
    horizon: int  # H
    r_max: float  # reward bound; values at step h+1 lie in [0, (H - h - 1) r_max]
    v_upper: float  # the paper's value bound H (times r_max): V in [0, v_upper]

    @property
    def next_value_bound(self) -> float:
        """``(H - h - 1) r_max``: the step's own bound on ``V_{h+1}`` (``Q_{h+1}`` is clipped
        to it); see :mod:`r2pvi.duals.ranges`."""
        return (self.horizon - self.h - 1) * self.r_max


class StepRule:
    """How an algorithm turns next-step values into this step's weights ``w_h (d,)``.

    Subclasses implement :meth:`__call__`. ``E`` is the step's ridge expectation operator
    and ``v`` the next-step values at the K sampled next states.
    """

    def __call__(self, E: RidgeExpectation, v: np.ndarray, ctx: StepContext) -> np.ndarray:
        raise NotImplementedError


@dataclass
class FittedModel:
    """The fitted state that defines every ``Q_h``.

    Attributes
    ----------
    weights : (H, d) ``theta_h + w_h``
    reward_weights : (H, d) ``theta_h`` (given or ridge-estimated)
    gram_cholesky : (H, d, d) lower Cholesky factors of ``Lambda_h``
    gram_inv_diag : (H, d) ``diag(Lambda_h^{-1})``
    next_state_values : (H, K) ``V_{h+1}`` at the sampled next states (0 at ``h = H-1``)
    """

    weights: np.ndarray
    reward_weights: np.ndarray
    gram_cholesky: np.ndarray
    gram_inv_diag: np.ndarray
    next_state_values: np.ndarray | None = None


def penalty_values(phi, kind: str, beta: float, inv_diag, chol) -> np.ndarray:
    """The pessimism penalty ``Gamma_h(phi)`` for features ``phi (..., d)``.

    - ``"l1"`` (paper, Thm. instance-dependent bound): ``beta sum_i |phi_i| sqrt([Lambda^-1]_ii)``
    - ``"l2"`` (the authors' code): ``beta sqrt(sum_i phi_i^2 [Lambda^-1]_ii)``
    - ``"elliptical"`` (PEVI): ``beta ||phi||_{Lambda^-1}``
    """
    if beta == 0.0:
        return np.zeros(phi.shape[:-1])
    lead = phi.shape[:-1]
    flat = phi.reshape(-1, phi.shape[-1])
    if kind == "l1":
        out = np.abs(flat) @ np.sqrt(inv_diag)
    elif kind == "l2":
        out = np.sqrt((flat * flat) @ inv_diag)
    elif kind == "elliptical":
        z = flat @ np.linalg.solve(chol, np.eye(chol.shape[0])).T  # rows L^{-1} phi, one GEMM
        out = np.sqrt(np.einsum("ij,ij->i", z, z))
    else:
        raise ValueError(f"penalty must be one of {PENALTIES}, got {kind!r}")
    return beta * out.reshape(lead)


def _q_step(phi, weights_h, kind, beta, inv_diag, chol, upper, known=None, nonneg=None):
    """``clip(phi^T w - Gamma(phi), 0, upper)``, with known values where not NaN."""
    lead = phi.shape[:-1]
    flat = phi.reshape(-1, phi.shape[-1])  # one GEMM, not a batch of small products
    if kind == "l1" and beta != 0.0:
        # One pass over the features for the linear part and the penalty together.
        scale = -beta * np.sqrt(inv_diag)
        if nonneg:
            both = flat @ np.stack([weights_h, scale], axis=1)
            q = both[:, 0] + both[:, 1]
        else:
            q = flat @ weights_h + np.abs(flat) @ scale
    else:
        q = flat @ weights_h - penalty_values(flat, kind, beta, inv_diag, chol)
    q = q.reshape(lead)
    np.clip(q, 0.0, upper, out=q)
    if known is not None:
        q = np.where(np.isnan(known), q, known)
    return q


def _max_over_actions(q: np.ndarray) -> np.ndarray:
    """``max_a q[:, a]``; a chain of ``maximum`` is faster than a reduction for few actions."""
    if q.shape[1] > 8:
        return q.max(axis=1)
    v = q[:, 0].copy()
    for a in range(1, q.shape[1]):
        np.maximum(v, q[:, a], out=v)
    return v


class _NextValue:
    """``V_{h+1} = max_a Q_{h+1}`` on a chunk of next-state features ``(n, A, d)``; the step
    source calls it chunk by chunk (or once on a feature table). A class, not a closure, so
    that Dask can ship it to the workers."""

    def __init__(self, weights_h, kind, beta, inv_diag, chol, upper):
        self.args = (weights_h, kind, beta, inv_diag, chol, upper)

    def __call__(self, feats, known, nonneg):
        return _max_over_actions(_q_step(feats, *self.args, known, nonneg))


def q_values_from_model(model: FittedModel, phi_all, h: int, *, penalty, beta, r_max,
                        known_values=None) -> np.ndarray:
    """``Q_h`` of a fitted model at features ``phi_all (n, A, d)`` -> ``(n, A)``."""
    H = model.weights.shape[0]
    return _q_step(
        phi_all,
        model.weights[h],
        penalty,
        beta,
        model.gram_inv_diag[h],
        model.gram_cholesky[h],
        (H - h) * r_max,
        known_values,
    )


def backward_induction(
    dataset: OfflineDataset,
    rule: StepRule,
    *,
    beta: float,
    gamma: float,
    penalty: str,
    r_max: float,
    reward_weights: np.ndarray | None = None,
    sample_weights: np.ndarray | None = None,
) -> FittedModel:
    """Run the backward induction of Algorithms 1-2 with ``rule`` estimating ``w_h``.

    Parameters
    ----------
    dataset : OfflineDataset
    rule : StepRule
        The algorithm: next-step values -> weights.
    beta, gamma, penalty, r_max
        Pessimism scale, ridge parameter, penalty form (see :func:`penalty_values`) and the
        reward bound (Q_h is clipped to ``[0, (H - h) r_max]``).
    reward_weights : (H, d), optional
        Known ``theta_h``; None estimates ``theta_h`` by ridge regression on the rewards.
    sample_weights : (H, K), optional
        Regression weights ``1 / sigma_h^2`` (variance-aware variants); None means 1.
    """
    H, d = dataset.horizon, dataset.n_features
    source = dataset._source  # the step-major data: in memory, on disk or in Dask arrays
    nonneg_phi = dataset._nonnegative_phi  # None: checked on a step's features when needed
    weights = np.zeros((H, d))
    thetas = np.zeros((H, d))
    chols = np.zeros((H, d, d))
    inv_diags = np.zeros((H, d))
    next_state_values = np.zeros((H, dataset.n_trajectories))
    v_upper = H * r_max
    step_buffer = None  # one step's (K, d) float64 features, reused when they are read
    try:
        for h in range(H - 1, -1, -1):
            phi = step_buffer = source.phi_step(h, step_buffer)  # next-state data: by chunk
            rewards = source.rewards_step(h)
            sw = None if sample_weights is None else sample_weights[h]
            chol = cholesky_gram(phi, gamma, sw)
            E = RidgeExpectation(phi, chol, sw, nonneg_phi)
            theta = E(rewards) if reward_weights is None else reward_weights[h]
            if h == H - 1:
                w = np.zeros(d)  # V_H = 0: the robust expectation of 0 is 0 for every divergence
            else:
                v_next = source.next_state_values(h, _NextValue(
                    weights[h + 1], penalty, beta, inv_diags[h + 1], chols[h + 1],
                    (H - h - 1) * r_max))
                next_state_values[h] = v_next
                w = rule(E, v_next, StepContext(h, H, r_max, v_upper))
            weights[h] = theta + w
            thetas[h] = theta
            chols[h] = chol
            inv_diags[h] = E.inverse_diagonal()
    finally:
        release()  # the duals' reusable work buffers
    return FittedModel(weights, thetas, chols, inv_diags, next_state_values)
