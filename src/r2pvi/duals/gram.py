"""The ridge Gram matrix ``Lambda = Phi^T W Phi + gamma I``, factored once per step.

:func:`cholesky_gram` and :func:`ridge_cholesky` give the lower Cholesky factor (a
:class:`GramMatrixError` naming ``gamma`` when there is none); :class:`GramFactor` factors
``Lambda`` in primal (d x d) or dual (n x n, Woodbury) form, for dense or sparse rows, and
applies ``Lambda^{-1}``: the ridge weights, ``diag(Lambda^{-1})``, the elliptical norms.
"""

from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp

from ._sparse_rows import (
    _scale_rows,
    _sparse_column_quadratic,
    _SparseProduct,
    _used_columns,
    _UsedFeaturesFactor,
)

__all__ = [
    "GramFactor",
    "GramMatrixError",
    "choose_form",
    "cholesky_gram",
    "cholesky_solve",
    "ridge_cholesky",
]

# NumPy's LAPACK only: NumPy and SciPy wheels bundle separate OpenBLAS builds whose thread
# pools spin against each other when calls alternate (docs/benchmarks.md). d is small, so
# generic solves on the triangular factors cost nothing next to forming the Gram matrix.


def cholesky_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``Lambda x = b`` given the lower Cholesky factor ``L`` of ``Lambda = L L^T``."""
    return np.linalg.solve(chol.T, np.linalg.solve(chol, b))


def cholesky_gram(phi: np.ndarray, gamma: float, weights: np.ndarray | None = None) -> np.ndarray:
    """Lower Cholesky factor of ``Lambda = sum_tau w_tau phi_tau phi_tau^T + gamma I``.

    The Gram matrix of Algorithms 1-2 (line 3), optionally weighted by ``w = 1/sigma^2``
    for the variance-aware variants. ``phi`` may be a ``scipy.sparse`` matrix (d x d result).
    """
    if sp.issparse(phi):
        xw = phi if weights is None else sp.diags(weights) @ phi
        gram = np.asarray((xw.T @ phi).toarray(), dtype=float)
    else:
        xw = phi if weights is None else phi * weights[:, None]
        gram = xw.T @ phi
    return ridge_cholesky(gram, gamma)


def ridge_cholesky(gram: np.ndarray, gamma: float) -> np.ndarray:
    """Lower Cholesky factor of ``gram + gamma I`` (``gram`` is modified), or a
    :class:`GramMatrixError` naming ``gamma`` when it does not exist."""
    gram[np.diag_indices_from(gram)] += gamma
    try:
        return np.linalg.cholesky(gram)
    except np.linalg.LinAlgError:
        raise GramMatrixError(
            f"the Gram matrix Lambda = Phi^T Phi + gamma I is not numerically positive "
            f"definite: gamma = {gamma!r} is too small for these collinear (rank-deficient) "
            "features; use a larger gamma (the default is 1.0)"
        ) from None


class GramMatrixError(np.linalg.LinAlgError):
    """The ridge Gram matrix has no Cholesky factor: gamma is too small for the features.

    A ``LinAlgError``, hence a ``ValueError``."""


FORMS = ("auto", "primal", "dual")

# From this size on, triangular inverses go through LAPACK's trtri (d^3/3 flops) rather than
# a generic solve against the identity (about 8x the flops; docs/large-feature-spaces.md).
# Below it, NumPy's LAPACK only (see the note above).
_TRTRI_FROM = 256


def _triangular_inverse(lower: np.ndarray) -> np.ndarray:
    """``L^{-1}`` of a lower-triangular ``L``."""
    n = lower.shape[0]
    if n < _TRTRI_FROM:
        return np.linalg.solve(lower, np.eye(n))
    from scipy.linalg import lapack

    inv, info = lapack.dtrtri(lower, lower=1)
    if info != 0:  # pragma: no cover - a Cholesky factor has a positive diagonal
        raise np.linalg.LinAlgError(f"triangular inverse failed (info={info})")
    return np.tril(inv)


def _lower_solve(lower: np.ndarray, b: np.ndarray, trans: str = "N") -> np.ndarray:
    """``L^{-1} b`` (``trans="N"``) or ``L^{-T} b`` (``"T"``) for a lower-triangular ``L``."""
    from scipy.linalg import solve_triangular

    return solve_triangular(lower, b, lower=True, trans=trans, check_finite=False)


def choose_form(n: int, d: int, sparse: bool = False) -> str:
    """Primal (d x d) or dual (n x n, Woodbury) factorization of ``Lambda``: dual when d > n.

    Counting multiply-adds, the primal costs ``n d^2 / 2`` (Gram) ``+ d^3 / 3`` (Cholesky and
    triangular inverse) and the dual ``n^2 d`` (Gram and ``C^{-1} Psi``) ``+ n^3 / 3``; the
    counts cross a little below d = n, but LAPACK's factorizations run slower than the
    Gram products (docs/large-feature-spaces.md), so the dual form whenever d > n. For
    sparse rows ``d`` is the number of *used* features (those some row stores an
    entry for): ``Lambda`` is ``gamma I`` off them, so the primal form factors a dense matrix
    of that size only (:class:`GramFactor`).
    """
    return "dual" if d > n else "primal"


class GramFactor:
    """Exact factorization of ``Lambda = Phi^T W Phi + gamma I`` in primal or dual form.

    With ``Psi = W^{1/2} Phi`` (n x d; dense or ``scipy.sparse``):

    - **primal** (``d x d``): ``Lambda = L L^T`` (Cholesky), ``L^{-1}`` by one triangular
      inverse; ``Lambda^{-1} b = L^{-T} L^{-1} b``, ``diag(Lambda^{-1})`` = column norms of
      ``L^{-1}``.
    - **dual** (``n x n``, Woodbury): ``G = Psi Psi^T + gamma I = C C^T``. Then
      ``Lambda^{-1} Psi^T = Psi^T G^{-1}`` (the push-through identity), so the ridge weights are
      ``Lambda^{-1} Phi^T W y = Psi^T G^{-1} W^{1/2} y`` with no cancellation, and
      ``Lambda^{-1} = (I - Psi^T G^{-1} Psi) / gamma`` gives ``diag(Lambda^{-1})`` and
      ``||x||^2_{Lambda^{-1}} = (||x||^2 - ||C^{-1} Psi x||^2) / gamma`` from the same factor.
      These two subtract quantities of size ``||x||^2``: relative error about
      ``eps * ||x||^2 / (gamma ||x||^2_{Lambda^{-1}})``, i.e. ``eps`` times the ratio of the
      data's coverage of ``x`` to ``gamma`` (1e-13 for counts up to 1e3 with ``gamma = 1``).
      The same holds for the weights when rows repeat (``Psi Psi^T`` singular): ``G^{-1}``
      amplifies its null space by ``1/gamma`` and ``Psi^T`` cancels it, leaving errors of about
      ``eps ||Psi||^2 / gamma``. For a tiny ``gamma`` force ``form="primal"``.

    ``form="auto"`` picks the cheaper one from the shapes (:func:`choose_form`); both give the
    same numbers to rounding.

    With sparse rows (tile coding: tens of thousands of features, a few hundred of them used at
    a step) the primal form works on the used features ``U`` only: no row of ``Phi`` has an
    entry off ``U``, so ``Lambda`` is block diagonal, ``Lambda_U = Phi_U^T W Phi_U + gamma I``
    (dense, ``|U| x |U|``, factored) and ``gamma I`` elsewhere; the weights are 0 off ``U``
    and ``diag(Lambda^{-1})`` is ``1 / gamma`` there. Exact, and it costs ``|U|^3`` instead of
    the dual's ``n^3`` when ``|U| < n``.

    Parameters
    ----------
    phi : ndarray or scipy.sparse matrix (n, d)
    gamma : float
        Ridge parameter (> 0).
    weights : ndarray (n,), optional
        Regression weights ``w >= 0`` (variance-aware variants); None means 1.
    form : {"auto", "primal", "dual"}

    Examples
    --------
    >>> import numpy as np
    >>> phi = np.random.default_rng(0).random((3, 5))          # n = 3 < d = 5: dual
    >>> f = GramFactor(phi, gamma=0.5)
    >>> f.form
    'dual'
    >>> lam = phi.T @ phi + 0.5 * np.eye(5)
    >>> bool(np.allclose(f.inverse_diagonal(), np.diag(np.linalg.inv(lam))))
    True
    """

    def __init__(self, phi, gamma: float, weights: np.ndarray | None = None, form: str = "auto"):
        if form not in FORMS:
            raise ValueError(f"form must be one of {FORMS}, got {form!r}")
        self.sparse = sp.issparse(phi)
        if self.sparse:
            phi = sp.csr_matrix(phi, dtype=float)
        self.phi = phi
        self.weights = weights
        self.gamma = float(gamma)
        self.n, self.d = phi.shape
        # Sparse rows: the primal form lives on the used features only (see the class notes).
        self.cols = _used_columns(phi) if self.sparse else None
        if form == "auto":
            form = choose_form(self.n, self.d if self.cols is None else self.cols.size)
        self.form = form
        self._linv = self._cinv = self._u = None
        if self.form == "primal":
            self.chol = cholesky_gram(self._phi_used, gamma, weights)
            return
        self.chol = None
        self.root = None if weights is None else np.sqrt(weights)
        psi = self.psi
        gram = psi @ psi.T
        gram = np.array(gram.toarray() if self.sparse else gram, dtype=float)
        gram[np.diag_indices_from(gram)] += gamma
        try:
            self.dual_chol = np.linalg.cholesky(gram)
        except np.linalg.LinAlgError:
            raise GramMatrixError(
                f"the Gram matrix Psi Psi^T + gamma I (dual form) is not numerically positive "
                f"definite: gamma = {gamma!r} is too small for these features; use a larger "
                "gamma (the default is 1.0)"
            ) from None

    @classmethod
    def from_cholesky(cls, phi, chol: np.ndarray, weights: np.ndarray | None = None,
                      gamma: float | None = None) -> GramFactor:
        """A primal factor from a given lower Cholesky factor of ``Lambda``."""
        self = cls.__new__(cls)
        self.sparse = sp.issparse(phi)
        self.phi, self.weights, self.chol = phi, weights, chol
        self.n, self.d = phi.shape
        self.gamma = gamma
        self.form = "primal"
        self.cols = None
        self._linv = self._cinv = self._u = None
        return self

    # ------------------------------------------------------------------ pieces
    @property
    def _phi_used(self):
        """The rows on the used features (all of them for dense rows; computed once)."""
        if self.cols is None:
            return self.phi
        if getattr(self, "_used_rows", None) is None:
            self._used_rows = self.phi[:, self.cols]
        return self._used_rows

    def _on_used(self, used_part, fill):
        """A ``(d, ...)`` array equal to ``fill`` off the used features and ``used_part`` on
        them (sparse-row primal form); ``used_part`` itself for dense rows."""
        if self.cols is None:
            return used_part
        out = np.full((self.d,) + used_part.shape[1:], fill, dtype=float) if np.isscalar(
            fill) else np.array(fill, dtype=float)
        out[self.cols] = used_part
        return out

    @property
    def psi(self):
        """``W^{1/2} Phi`` (n x d), the rows that enter the Gram matrix (computed once)."""
        root = getattr(self, "root", None)
        if root is None:
            return self.phi
        if getattr(self, "_psi", None) is None:
            self._psi = sp.diags(root) @ self.phi if self.sparse else self.phi * root[:, None]
        return self._psi

    @property
    def linv(self) -> np.ndarray:
        """``L^{-1}`` (primal form; computed once)."""
        if self._linv is None:
            self._linv = _triangular_inverse(self.chol)
        return self._linv

    @property
    def cinv(self) -> np.ndarray:
        """``C^{-1}`` with ``C C^T = Psi Psi^T + gamma I`` (dual form; computed once)."""
        if self._cinv is None:
            self._cinv = _triangular_inverse(self.dual_chol)
        return self._cinv

    @property
    def u(self) -> np.ndarray:
        """``U = C^{-1} Psi`` (n x d, dense; dual form; computed once): one triangular solve
        (``n^2 d / 2`` multiply-adds, half a GEMM) for dense features."""
        if self._u is None:
            psi = self.psi
            if self.sparse:
                self._u = np.asarray((psi.T @ self.cinv.T).T)
            else:
                self._u = _lower_solve(self.dual_chol, psi)
        return self._u

    @property
    def z(self) -> np.ndarray:
        """``Z = G^{-1} Psi`` (n x d, dense features, dual form; computed once): one GEMM gives
        both the weight matrix ``M = Z^T W^{1/2}`` and ``diag(Psi^T G^{-1} Psi)``."""
        if getattr(self, "_z", None) is None:
            if self.sparse:
                self._z = self.ginv @ self.psi
            else:  # C^-T U: one triangular solve (n^2 d / 2), no n x n inverse
                self._z = _lower_solve(self.dual_chol, self.u, trans="T")
        return self._z

    @property
    def ginv(self) -> np.ndarray:
        """``G^{-1} = C^{-T} C^{-1}`` (n x n; dual form; computed once)."""
        if getattr(self, "_ginv", None) is None:
            self._ginv = self.cinv.T @ self.cinv
        return self._ginv

    def _primal_solve(self, b):
        """``Lambda^{-1} b = L^{-T} L^{-1} b``. Small d: two generic solves on ``L`` (an LU
        each, nothing kept). From ``_TRTRI_FROM`` on, a generic solve costs ``O(d^3)`` per
        call, so the triangular inverse is formed once (``d^3 / 3``) and every solve is two
        products."""
        if self.chol.shape[0] < _TRTRI_FROM:
            return cholesky_solve(self.chol, b)
        linv = self.linv
        return linv.T @ (linv @ b)

    def _dual_apply(self, z):
        """``G^{-1} z = C^{-T} C^{-1} z`` for ``z (n,)`` or ``(n, m)``."""
        ci = self.cinv
        return ci.T @ (ci @ z)

    def active_features(self) -> np.ndarray | None:
        """Indices of the features some row uses (sparse rows), None for dense rows."""
        if not self.sparse:
            return None
        return self.cols  # found once, when the factor was formed

    def restrict(self, cols: np.ndarray) -> GramFactor:
        """The factor of the features ``cols`` alone, for a dual-form factor whose other
        features are unused (zero columns): ``Lambda`` is then block diagonal, ``Psi Psi^T``
        and its factor are unchanged and shared."""
        if self.form != "dual" and self.cols is None:
            raise ValueError("restrict needs the dual form or sparse rows")
        new = copy.copy(self)
        new._used_rows = None
        new.phi, new.d = self.phi[:, cols], len(cols)
        if self.cols is not None:  # the used features, renumbered (they keep their order)
            where = np.full(self.d, -1)
            where[np.asarray(cols)] = np.arange(len(cols))
            pos = where[self.cols]
            if np.any(pos < 0) or np.any(np.diff(pos) <= 0):
                raise ValueError("restrict: cols must hold every used feature, in order")
            new.cols = pos
        if self.form == "primal":  # the used features keep their factor
            return new
        new._psi = None
        new._u = None if self._u is None else self._u[:, cols]
        new._z = None if getattr(self, "_z", None) is None else self._z[:, cols]
        return new

    # ------------------------------------------------------------------ the operator
    def regress(self, y: np.ndarray) -> np.ndarray:
        """Ridge weights ``Lambda^{-1} Phi^T W y`` for ``y (n,)`` or ``(n, m)``."""
        if self.form == "primal":
            yw = y if self.weights is None else (y.T * self.weights).T
            w = self._primal_solve(np.asarray(self._phi_used.T @ yw))
            return self._on_used(w, 0.0)  # unused features: Phi^T y = 0 there
        ys = y if self.root is None else (y.T * self.root).T
        if not self.sparse:  # Psi^T G^-1 = U^T C^-1 with U (needed for the diagonal anyway)
            return self.u.T @ _lower_solve(self.dual_chol, ys)
        return np.asarray(self.psi.T @ self._dual_apply(ys))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``Lambda^{-1} b`` for ``b (d,)`` or ``(d, m)``."""
        if self.form == "primal":
            if self.cols is None:
                return self._primal_solve(b)
            return self._on_used(self._primal_solve(b[self.cols]), b / self.gamma)
        if not self.sparse:
            u = self.u
            return (b - u.T @ (u @ b)) / self.gamma
        psi = self.psi
        return (b - np.asarray(psi.T @ self._dual_apply(np.asarray(psi @ b)))) / self.gamma

    def matrix(self) -> np.ndarray:
        """The weight matrix ``M = Lambda^{-1} Phi^T W`` (d x n, dense)."""
        if self.form == "primal":
            phi = self._phi_used
            xw = phi if self.weights is None else _scale_rows(phi, self.weights)
            if self.sparse:  # Lambda_U^{-1} (|U|^3) times sparse rows: nnz |U|, not |U|^2 n
                linv = self.linv
                return self._on_used(np.asarray(xw @ (linv.T @ linv)).T, 0.0)
            return self.linv.T @ (self.linv @ xw.T)
        if not self.sparse:
            m = np.array(self.z.T, order="C")  # a copy: z stays cached
            return m if self.root is None else np.multiply(m, self.root, out=m)
        g = self.ginv if self.root is None else self.ginv * self.root
        return np.asarray(self.psi.T @ g)

    def inverse_diagonal(self) -> np.ndarray:
        """``diag(Lambda^{-1})`` without forming ``Lambda^{-1}``."""
        if self.form == "primal":
            linv = self.linv
            return self._on_used(np.einsum("ij,ij->j", linv, linv), 1.0 / self.gamma)
        if self.sparse:
            quad = _sparse_column_quadratic(self.psi, self.ginv)
        elif getattr(self, "_z", None) is not None:  # the weight matrix was formed: n d more
            quad = np.einsum("ij,ij->j", self.psi, self._z)
        else:
            u = self.u
            quad = np.einsum("ij,ij->j", u, u)
        return np.clip(1.0 - quad, 0.0, 1.0) / self.gamma

    def elliptical_factor(self):
        """``(R, c0, c1)`` with ``||x||^2_{Lambda^{-1}} = c0 ||x||^2 + c1 ||R x||^2``.

        Primal: ``(L^{-1}, 0, 1)``; dual: ``(C^{-1} Psi, 1/gamma, -1/gamma)``. Acting needs only
        these products: computed once by ``fit``, never a factorization per call.
        """
        if self.form == "primal":
            if self.cols is None:
                return self.linv, 0.0, 1.0
            return _UsedFeaturesFactor(self.linv, self.cols, self.gamma), 0.0, 1.0
        r = self.u if not self.sparse else _SparseProduct(self.cinv, self.psi)
        return r, 1.0 / self.gamma, -1.0 / self.gamma

