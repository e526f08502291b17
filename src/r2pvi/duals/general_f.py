"""The regularized dual for a general f-divergence (paper, Algorithm 1), one per factor.

:func:`f_regularized` maximizes ``alpha - lam E_i[f*((alpha - V)/lam)]`` over ``alpha`` by a
safeguarded golden-section search, for any :class:`~r2pvi.duals.FDivergence`; the closed forms
(TV, KL, chi^2) are in :mod:`r2pvi.duals.regularized`.
"""

from __future__ import annotations

import numpy as np

from .fdivergence import FDivergence
from .operator import ExpectationOperator
from .regularized import row_sums

__all__ = ["f_regularized"]


def f_regularized(
    E: ExpectationOperator,
    v: np.ndarray,
    lam: float,
    divergence: FDivergence,
    v_min=None,
    xtol: float = 1e-11,
    max_iter: int = 300,
) -> np.ndarray:
    """General f: ``sup_alpha alpha - lam E_i[f*((alpha - V)/lam)]`` (paper, Algorithm 1).

    Every expectation is estimated by the operator, the constant ``alpha`` included: the
    objective is ``E_i[alpha - lam f*((alpha - V)/lam)] = s_i alpha - lam E_i[f*(...)]`` with
    ``s_i = E_i[1]`` (:func:`row_sums`; 1 for a distribution). So, like the closed forms,
    the ridge estimate is ``s_i`` times the dual under the row-normalized weights, and
    ``lam -> inf`` gives the plain ridge estimate. (Algorithm 1 as printed leaves ``alpha``
    unshrunk, which adds ``(1 - s_i) alpha*`` — unbounded in ``lam`` for KL.)

    Solved per factor by a vectorized golden-section search on an interval that contains the
    maximizer ``alpha*`` of the exact dual for any distribution ``p`` (weights ``M_i / s_i``):

    - ``[V_min + lam lo, V_max + lam hi]``, ``[lo, hi]`` the subdifferential of f at 1
      (``E_p[(f*)'] = 1`` at ``alpha*`` and ``(f*)'`` is at most 1 left of ``lo`` and at
      least 1 right of ``hi``);
    - ``alpha* <= V_min + lam dom``, the right end of the conjugate's domain;
    - ``alpha* <= V_j + lam f'_+(1 / p_j)`` for every point j: the optimal perturbed
      distribution ``p_j (f*)'((alpha* - V_j)/lam)`` puts mass at most 1 on j, and
      ``(f*)' = (f')^{-1}``. ``f'_+`` is the built-ins' exact right derivative
      (:meth:`FDivergence.right_derivative`; a right secant, an upper bound, for user-defined
      f), so the bound is safe. With signed ridge weights this bound is what keeps
      ``alpha`` away from the edge of the domain, where a negative weight times
      ``f* -> inf`` makes the estimated objective unbounded (e.g. Hellinger:
      ``alpha* <= V_j + lam (1 - sqrt(p_j))``).

    The search is safeguarded: non-finite objective values count as ``-inf``, both interval
    ends are evaluated and the best point seen is returned (the ridge-estimated objective
    need not be concave). ``v_min`` is the minimum of V over all states (it matters only when
    f grows linearly, e.g. TV and Hellinger); None takes the minimum of ``v``. With a
    true-model operator this equals the closed forms (TV, KL, chi^2).

    Computed around the tangent at ``s0 = f'(1)`` (:attr:`FDivergence.centre`): with ``alpha =
    V_min + lam s0 + beta`` the objective is ``E_i V - lam E_i[r((beta + V_min - V)/lam)]``,
    ``r`` the conjugate's remainder (:meth:`FDivergence.conjugate_remainder`, ``>= 0``), so
    no two terms of size ``lam`` cancel (the direct form ``s_i alpha - lam E_i[f*]`` loses about
    ``lam / |V|`` of the digits) and a distribution's value never exceeds ``E V``. The
    result is capped at the plain estimate ``E_i V`` (signed ridge weights could pass it).
    """
    v = np.asarray(v, dtype=float)
    floor = float(np.min(v)) if v_min is None else min(float(v_min), float(np.min(v)))
    spread = float(np.max(v)) - floor
    s_lo, s_hi = divergence.slope_at_one
    s0 = divergence.centre
    # beta = alpha - floor - lam s0: the interval of the docstring, relative to that origin
    lo = lam * (s_lo - s0)
    hi = spread + lam * (s_hi - s0)
    if np.isfinite(divergence.domain_max):
        edge = lam * (divergence.domain_max - s0)
        if divergence.domain_open:
            edge -= 1e-12 * max(1.0, abs(edge), abs(floor))
        hi = min(hi, edge)
    m = E.matrix
    d = m.shape[0]
    s = row_sums(E)
    hi = np.maximum(np.minimum(hi, _mass_bound(m, s, v, lam, divergence, floor, s0)), lo)
    plain = m @ v
    y = floor - v  # beta + y is lam times the conjugate's argument minus s0

    # A point with no weight contributes nothing, even where f* is infinite there (else
    # 0 * inf = NaN would hide every alpha above V_j + lam dom of a point off the support).
    off = m == 0.0
    off = off if off.any() else None

    def objective(beta):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            rem = divergence.conjugate_remainder((beta[:, None] + y[None, :]) / lam)
            if off is not None:
                rem = np.where(off, 0.0, rem)
            val = plain - lam * np.einsum("ij,ij->i", m, rem)
        return np.where(np.isfinite(val), val, -np.inf)

    invphi = (np.sqrt(5.0) - 1.0) / 2.0
    a = np.full(d, lo)
    bnd = hi.copy()
    x1 = bnd - invphi * (bnd - a)
    x2 = a + invphi * (bnd - a)
    f1, f2 = objective(x1), objective(x2)
    best_f = np.maximum.reduce([objective(a), objective(bnd), f1, f2])
    scale = 1.0 + spread + abs(floor)
    for _ in range(max_iter):
        if np.all(bnd - a <= xtol * scale):
            break
        go_left = f1 >= f2  # keep [a, x2]
        a = np.where(go_left, a, x1)
        bnd = np.where(go_left, x2, bnd)
        new_x = np.where(go_left, bnd - invphi * (bnd - a), a + invphi * (bnd - a))
        new_f = objective(new_x)
        x1, x2, f1, f2 = (
            np.where(go_left, new_x, x2),
            np.where(go_left, x1, new_x),
            np.where(go_left, new_f, f2),
            np.where(go_left, f1, new_f),
        )
        best_f = np.maximum(best_f, new_f)
    # At most the plain estimate E_i V (the value at mu = mu0, above every exact dual; signed
    # ridge weights make the estimated objective non-concave, and its sup can pass it).
    # Free: ``plain`` is at hand.
    return np.minimum(best_f, plain)


def _mass_bound(m, s, v, lam, divergence, floor, s0):
    """``min_j (V_j - floor) + lam (f'_+(max(s_i / |M_ij|, 1)) - s0)`` per factor: the bound
    ``alpha* <= V_j + lam f'_+(1/p_j)`` measured from ``floor + lam s0`` (``+inf`` where it
    says nothing).

    ``f'_+`` is the divergence's right derivative (:meth:`FDivergence.right_derivative`:
    exact for the built-ins, else a right secant, an upper bound as f is convex, so the
    bound stays valid); points with no weight, non-positive ``s_i`` and non-finite slopes are
    skipped (a looser interval, never a wrong one).
    """
    absm = np.abs(m)
    use = (absm > 1e-12 * absm.max(axis=1, keepdims=True)) & (s[:, None] > 0.0)
    if not use.any():
        return np.full(m.shape[0], np.inf)
    with np.errstate(all="ignore"):
        # 1/p_j >= 1 for a distribution; signed weights can have |M_ij| > s_i.
        y = np.maximum(np.where(use, s[:, None] / np.where(use, absm, 1.0), 1.0), 1.0)
        cap = (v[None, :] - floor) + lam * (divergence.right_derivative(y) - s0)
    cap = np.where(use & np.isfinite(cap), cap, np.inf)
    return cap.min(axis=1)
