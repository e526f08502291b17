"""Products of a Gram factor with sparse rows (``scipy.sparse``): the used features, the
elliptical factors of the sparse primal and dual forms, the diagonal of ``Lambda^{-1}``."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _used_columns(phi) -> np.ndarray:
    """The features some sparse row stores an entry for (sorted)."""
    return np.unique(sp.csr_matrix(phi).indices)


class _UsedFeaturesFactor:
    """The elliptical factor of a sparse-row primal form: ``Lambda`` is block diagonal,
    ``Lambda_U`` on the used features ``U`` and ``gamma I`` off them, so
    ``||x||^2_{Lambda^{-1}} = ||L_U^{-1} x_U||^2 + ||x_{not U}||^2 / gamma``. :meth:`apply_rows`
    returns ``[L_U^{-1} x_U, ||x_{not U}|| / sqrt(gamma)]`` per row, whose squared norm is that."""

    def __init__(self, linv, cols, gamma):
        self.linv, self.cols, self.gamma = linv, np.asarray(cols), float(gamma)

    def apply_rows(self, x):
        xs = sp.csr_matrix(x) if sp.issparse(x) else np.asarray(x)
        used = xs[:, self.cols]
        sq_all = np.asarray(xs.multiply(xs).sum(axis=1) if sp.issparse(xs) else
                            np.einsum("ij,ij->i", xs, xs)).ravel()
        used_d = used.toarray() if sp.issparse(used) else used
        rest = np.maximum(sq_all - np.einsum("ij,ij->i", used_d, used_d), 0.0)
        return np.hstack([used_d @ self.linv.T, np.sqrt(rest / self.gamma)[:, None]])


def _scale_rows(x, w):
    return sp.diags(w) @ x if sp.issparse(x) else x * w[:, None]


class _SparseProduct:
    """``R = C^{-1} Psi`` kept as its two factors (``Psi`` sparse): ``R @ x^T`` without
    forming the dense n x d matrix."""

    def __init__(self, cinv, psi):
        self.cinv, self.psi = cinv, sp.csr_matrix(psi)
        self.shape = (cinv.shape[0], psi.shape[1])

    def apply_rows(self, x):
        """``(R x_j)_j`` for rows ``x (m, d)``: ``(m, n)``."""
        return np.asarray((self.psi @ x.T).T @ self.cinv.T) if not sp.issparse(x) else \
            np.asarray((x @ self.psi.T).toarray() @ self.cinv.T)


def _sparse_column_quadratic(psi, ginv: np.ndarray) -> np.ndarray:
    """``diag(Psi^T G^{-1} Psi)`` for sparse ``Psi (n, d)``, on the used columns only:
    ``Z = Psi_A^T G^{-1}`` (``nnz(Psi) n`` flops, ``|A| x n`` dense for the ``|A|`` used
    columns), then the sum of ``Psi_A^T * Z`` over the non-zeros; unused columns give 0."""
    csc = sp.csc_matrix(psi)
    out = np.zeros(csc.shape[1])
    used = np.flatnonzero(np.diff(csc.indptr))
    if used.size == 0:
        return out
    sub_t = csc[:, used].T.tocsr()  # (|A|, n)
    z = np.asarray(sub_t @ ginv)
    out[used] = np.asarray(sub_t.multiply(z).sum(axis=1)).ravel()
    return out
