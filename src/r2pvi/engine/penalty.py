"""The pessimism penalty ``Gamma_h(phi)`` of a fitted step: "l1", "l2" or "elliptical"."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..data.storage.sparse_rows import flat_rows

__all__ = ["PENALTIES", "penalty_values", "elliptical_norms"]

PENALTIES = ("l1", "l2", "elliptical")


def elliptical_norms(flat, factor) -> np.ndarray:
    """``||x||_{Lambda^{-1}}`` of rows ``x`` of ``flat (m, d)`` (dense or sparse) from the
    fitted factor ``(R, c0, c1)``: one product with ``R``, no factorization."""
    r, c0, c1 = factor
    rx = r.apply_rows(flat) if hasattr(r, "apply_rows") else np.asarray(flat @ r.T)
    sq = c1 * np.einsum("ij,ij->i", rx, rx)
    if c0:
        sq += c0 * _row_sumsq(flat)
    return np.sqrt(np.maximum(sq, 0.0))


def _row_sumsq(flat):
    if sp.issparse(flat):
        return np.asarray(flat.multiply(flat).sum(axis=1)).ravel()
    return np.einsum("ij,ij->i", flat, flat)


def penalty_values(phi, kind: str, beta: float, inv_diag, ellip=None) -> np.ndarray:
    """The pessimism penalty ``Gamma_h(phi)`` for features ``phi (..., d)``.

    - ``"l1"`` (paper, Thm. instance-dependent bound): ``beta sum_i |phi_i| sqrt([Lambda^-1]_ii)``
    - ``"l2"`` (the authors' code): ``beta sqrt(sum_i phi_i^2 [Lambda^-1]_ii)``
    - ``"elliptical"`` (PEVI): ``beta ||phi||_{Lambda^-1}``, from the fitted factor ``ellip``
      (see :func:`elliptical_norms`)
    """
    flat, lead = flat_rows(phi)
    if beta == 0.0:
        return np.zeros(lead)
    if kind == "l1":
        out = abs(flat) @ np.sqrt(inv_diag)
    elif kind == "l2":
        sq = flat.multiply(flat) if sp.issparse(flat) else flat * flat
        out = np.sqrt(sq @ inv_diag)
    elif kind == "elliptical":
        out = elliptical_norms(flat, ellip)
    else:
        raise ValueError(f"penalty must be one of {PENALTIES}, got {kind!r}")
    return beta * np.asarray(out).reshape(lead)

