"""The fitted model and ``Q_h`` from it: ``clip(phi^T w_h - Gamma_h(phi), 0, (H - h) r_max)``,
at any features (acting) or at the sampled next states, maximized over actions (the next
step's values ``V_{h+1}`` that the backward induction regresses)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.storage._finite import check_next_products
from ..data.storage.sparse_rows import flat_rows
from .penalty import penalty_values

__all__ = ["FittedModel", "q_values_from_model"]


@dataclass
class FittedModel:
    """The fitted state that defines every ``Q_h``.

    Attributes
    ----------
    weights : (H, d) ``theta_h + w_h``
    reward_weights : (H, d) ``theta_h`` (given or ridge-estimated)
    gram_inv_diag : (H, d) ``diag(Lambda_h^{-1})`` (the "l1"/"l2" penalties)
    elliptical : list of H ``(R_h, c0_h, c1_h)`` or None
        ``||phi||^2_{Lambda_h^{-1}} = c0 ||phi||^2 + c1 ||R_h phi||^2`` (the "elliptical"
        penalty; see :meth:`~r2pvi.duals.GramFactor.elliptical_factor`), computed once by the
        fit so that acting never factors a matrix. None when the penalty does not need it.
        With ``time_homogeneous`` every entry is the same object.
    next_state_values : (H, n) ``V_{h+1}`` at the sampled next states (0 at ``h = H-1``);
        ``(0, n)`` for a pooled fit (``n = P K`` rows, ``H P K`` numbers) unless the value
        moments were asked for
    value_moments : (H, d, 2) ``E_h([U, U^2])``, ``U = V_{h+1} / r_max``: the ridge estimates
        of the first two moments of the next-step value, in units of ``r_max`` (finite for any
        finite ``r_max``), under step h's operator (variance-aware variants)
    diagnostics : :class:`~r2pvi.engine.diagnostics.FitDiagnostics` or None
        What the fit saw of its regressions (rows, shrinkage, absorbing transitions)
    """

    weights: np.ndarray
    reward_weights: np.ndarray
    gram_inv_diag: np.ndarray
    elliptical: list | None = None
    next_state_values: np.ndarray | None = None
    value_moments: np.ndarray | None = None
    diagnostics: object | None = None


def q_values_from_model(model: FittedModel, phi_all, h: int, *, penalty, beta, r_max,
                        known_values=None) -> np.ndarray:
    """``Q_h`` of a fitted model at features ``phi_all (n, A, d)`` -> ``(n, A)``.

    Costs ``O(n A d)`` plus the penalty (``O(n A d r)`` for the elliptical one with the
    fitted ``r x d`` factor); nothing is factored or inverted here.
    """
    H = model.weights.shape[0]
    ellip = None if model.elliptical is None else model.elliptical[h]
    return _q_step(
        phi_all,
        model.weights[h],
        penalty,
        beta,
        model.gram_inv_diag[h],
        ellip,
        (H - h) * r_max,
        known_values,
    )


def _q_step(phi, weights_h, kind, beta, inv_diag, ellip, upper, known=None, nonneg=None,
            check=False):
    """``clip(phi^T w - Gamma(phi), 0, upper)``, with known values where not NaN.

    ``ellip`` is the step's elliptical factor (only read by the "elliptical" penalty);
    ``phi`` is ``(..., d)`` dense or a
    :class:`~r2pvi.data.storage.sparse_rows.StackedSparse`. ``check`` refuses non-finite
    features where no value is known, and infinite known values
    (:func:`~r2pvi.data.storage._finite.check_next_products`), before the clip would hide them.
    """
    flat, lead = flat_rows(phi)  # one GEMM, not a batch of small products
    if kind == "l1" and beta != 0.0:
        scale = -beta * np.sqrt(inv_diag)
        if nonneg:  # |phi| = phi: one matrix-vector product, cheaper than an n x 2 GEMM
            q = np.asarray(flat @ (weights_h + scale))
        else:
            q = np.asarray(flat @ weights_h) + abs(flat) @ scale
    else:
        q = np.asarray(flat @ weights_h) - penalty_values(flat, kind, beta, inv_diag, ellip)
    q = np.asarray(q).reshape(lead)
    if check and isinstance(phi, np.ndarray):
        check_next_products(q, phi, known)
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

    def __init__(self, weights_h, kind, beta, inv_diag, chol, upper, check=False):
        self.args = (weights_h, kind, beta, inv_diag, chol, upper)
        # refuse non-finite features (data.storage._finite.NonFiniteRows): data not checked when
        # the dataset was built
        self.check = bool(check)

    def __call__(self, feats, known, nonneg):
        return _max_over_actions(_q_step(feats, *self.args, known, nonneg, self.check))

    def linear(self, nonneg) -> tuple[np.ndarray, float] | None:
        """``(u, upper)`` when ``V = clip(max_a phi_a^T u, 0, upper)`` on features with no known
        values (no penalty, or the "l1" penalty on non-negative features: ``|phi| = phi``), so
        that a source can compute it as one matrix-vector product per chunk and one clip at the
        end (the same numbers: ``clip`` is monotone, so it commutes with the max); else None."""
        weights_h, kind, beta, inv_diag, _, upper = self.args
        if beta == 0.0:
            return np.asarray(weights_h, dtype=float), upper
        if kind == "l1" and nonneg:  # the vector _q_step forms
            return weights_h + -beta * np.sqrt(inv_diag), upper
        return None

