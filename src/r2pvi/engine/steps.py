"""Step providers: how a step's rows reach its ridge operator.

Per-step fits of dense features whose Gram matrix is factored in primal form accumulate the
operator chunk by chunk (:class:`ChunkedRidgeExpectation`, never holding the step's rows);
the others factor a step's rows whole (:func:`_factor`), or, with pooled steps
(:func:`pooled_steps`), the rows of every step once.
"""

from __future__ import annotations

import numpy as np

from ..data.storage._finite import FIELDS
from ..duals.gram import GramFactor, GramMatrixError, choose_form, ridge_cholesky
from ..duals.operator import RidgeExpectation

__all__ = ["ChunkedRidgeExpectation", "pooled_steps"]


class _Rows:
    """Stands for the ``(K, d)`` rows a streamed factor does not hold (only their shape)."""

    def __init__(self, shape):
        self.shape = shape


class ChunkedRidgeExpectation(RidgeExpectation):
    """Step h's ridge operator accumulated chunk by chunk over the trajectories of a step
    source: ``Lambda = sum_c Phi_c^T W_c Phi_c + gamma I`` and
    ``E(y) = Lambda^{-1} sum_c Phi_c^T W_c y_c`` (Algorithm 1, lines 3-4), all sums in float64.

    Nothing of the step's features is held: each call reads them once, a chunk at a time
    (``source.phi_chunks``); the first call also forms ``Lambda`` in the same pass, and the
    columns registered with :meth:`include` ride along with it (the engine registers the
    rewards and the value moments, so a TV or PEVI step reads its features once). ``E(1)``
    (:meth:`total_weights`, :meth:`with_total_weights`: KL) is ``Lambda^{-1}`` of the column
    sums ``Phi^T W 1``, stored with the data or accumulated with the rule's regression in
    the same read. The primal (d x d) factor only, for dense features.

    Rules that need more than ``E(y)`` (explicit weight rows or columns, sorted blocks,
    truncation cumulants: chi^2, DRPVI, DRVI-L, KL's exact fallback for tiny moments) reach
    for :attr:`phi`; the operator then reads the step's ``(K, d)`` float64 features into one
    reused buffer and behaves as :class:`~r2pvi.duals.RidgeExpectation` from there on.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi.storage import ArrayField, StepSource, StoredNext
    >>> rng = np.random.default_rng(0)
    >>> phi = rng.random((2, 50, 3))                       # (H, K, d), step-major
    >>> src = StepSource(ArrayField(phi), ArrayField(rng.random((2, 50))),
    ...                  StoredNext(ArrayField(rng.random((2, 50, 2, 3)))), chunk=16)
    >>> E = ChunkedRidgeExpectation(src, h=1, gamma=1.0)
    >>> y = rng.random(50)
    >>> x = phi[1]                                         # the normal equations
    >>> bool(np.allclose(E(y), np.linalg.solve(x.T @ x + np.eye(3), x.T @ y)))
    True
    >>> E.passes                                           # Lambda and E(y): one read
    1
    """

    def __init__(self, source, h: int, gamma: float, weights=None,
                 nonnegative_features=None, buffers: dict | None = None):
        self.source, self.h, self.gamma = source, int(h), float(gamma)
        self.buffers = {} if buffers is None else buffers
        self._factor = None
        self._rows = None
        self._sums = None  # Phi^T W 1 (d,), accumulated with Lambda (E(1) = Lambda^-1 of it)
        self._want_sums = False
        self._pending: list[np.ndarray] = []
        self._done: list[tuple[np.ndarray, np.ndarray]] = []
        self.passes = 0  # reads of the step's features (a diagnostic)
        # Whether the step's features are known finite: checked when the dataset was built,
        # or by the sums of a pass (see _check_sums)
        self._finite = "phi" in getattr(source, "checked", FIELDS)
        super().__init__(_Rows((source.n_trajectories, source.n_features)), None, weights,
                         nonnegative_features)

    def _hold(self, phi, chol) -> None:
        """Nothing is held yet: the factor and the rows are formed when first asked
        (:attr:`factor`, :attr:`phi`); dense rows, the primal form."""
        self.primal_dense = True

    # ------------------------------------------------------------------ lazy pieces
    @property
    def factor(self) -> GramFactor:
        """The primal factor of ``Lambda`` (one pass over the features when first asked)."""
        if self._factor is None:
            self._pass(None)
        return self._factor

    @property
    def chol(self) -> np.ndarray:
        return self.factor.chol

    @property
    def phi(self) -> np.ndarray:
        """The step's ``(K, d)`` float64 features, read once into a reused buffer (the
        full path, for rules that need explicit rows)."""
        if self._rows is None:
            rows = self.source.phi_step(self.h, self.buffers.get("phi"))
            self.buffers["phi"] = rows
            formed = None
            if self._factor is None:
                w = self.weights
                gram = None if w is not None else self.source.gram(self.h)
                if gram is None:
                    gram = formed = (rows if w is None else rows * w[:, None]).T @ rows
                    self._check_sums([formed], rows)
                    if w is None:
                        self.source.remember_gram(self.h, gram)
                self._factor = _primal_factor(gram, self.gamma, w, rows.shape)
            if formed is None:  # the rows' own sums (one pass in memory) when not known finite
                self._check_sums([np.add.reduce(rows, axis=0)] if not self._finite else [],
                                 rows)
            self._factor.phi = rows  # from now on a plain primal factor over the rows
            self._rows = rows
        return self._rows

    def rows(self, dims=None) -> np.ndarray:
        self.phi  # noqa: B018 - explicit rows need the step's features in memory
        return super().rows(dims)

    def total_weights(self) -> np.ndarray:
        """``E(1) = Lambda^{-1} Phi^T W 1`` from the column sums ``Phi^T W 1``, which ride along
        with ``Lambda`` (stored with the data, kept from an earlier pass, or, for rows that
        sum to 1, the row sums of the Gram matrix ``Phi^T W Phi 1_d``): a ``d x d`` solve; a
        pass of its own only when none is known."""
        if self._total is None:
            if self._sums is None and self.weights is None:
                self._sums = self.source.phi_sums(self.h)
            if self._sums is None:
                if self._rows is not None:
                    return super().total_weights()
                self._want_sums = True
                self._pass(None)
            self._total = self._solve_sums(self._sums)
        return self._total.copy()

    def with_total_weights(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y), E(1))`` in one read of the step's features (none for ``E(1)`` when the
        column sums are known)."""
        if self._rows is None:
            self._want_sums = True  # accumulated with E(y) if not known
        return self(y), self.total_weights()

    def pair_with_total_weights(self, y1: np.ndarray, y2: np.ndarray):
        """``(E(y1), E(y2), E(1))`` in one read of the step's features (``E(1)`` from the
        column sums: known, or accumulated in the same read)."""
        if self._rows is not None:
            return super().pair_with_total_weights(y1, y2)
        if not any(y2 is p for p in self._pending):
            self.include(y2)
        e1, s = self.with_total_weights(y1)
        return e1, self(y2), s

    def include(self, y: np.ndarray) -> None:
        """Register ``y (n,)`` or ``(n, m)``: its product ``Phi^T W y`` is accumulated with
        the next pass, and ``E(y)`` (the same array object) then costs no read."""
        self._pending.append(y)

    # ------------------------------------------------------------------ the operator
    def apply_pair(self, y1: np.ndarray, y2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y1), E(y2))`` in one read of the step's features."""
        if self._rows is not None:
            return super().apply_pair(y1, y2)
        for y in (y1, y2):
            if not any(y is p for p in self._pending) and not any(
                    y is done for done, _ in self._done):
                self.include(y)
        return self(y1), self(y2)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        if any(p is y for p in self._pending):
            self._pass(None)
        for done, value in self._done:
            if done is y:
                return value.copy()
        if self._rows is not None:
            return super().__call__(y)
        return self._pass(y)

    def _pass(self, y):
        """One read of the step's features: ``Lambda`` (if not formed yet) and ``Phi^T W y``
        for ``y`` and every registered column; returns ``E(y)`` (None without ``y``)."""
        d = self.n_dims
        # Rows summing to 1 (validated): Phi^T W 1 = Phi^T W Phi 1_d, the row sums of the
        # Gram matrix (a d x d sum, no product per chunk); see StepSource.unit_rows.
        unit = self.source.unit_rows and self._want_sums
        if self._factor is None and self.weights is None:
            known = self.source.gram(self.h)  # stored with the data, or from an earlier fit
            if known is not None:
                if unit and self._sums is None:
                    self._sums = known.sum(axis=1)
                self._factor = _primal_factor(known, self.gamma, None, (self.n_points, d))
        if self._sums is None and self.weights is None:
            self._sums = self.source.phi_sums(self.h)
        # Phi^T W 1 when a rule asked for E(1) (with_total_weights: KL), in the same pass as
        # its regression; not for rules that never use it (one more matrix-vector product per
        # chunk, measured 2-5% of a TV fit in memory).
        colsum = np.zeros(d) if self._sums is None and self._want_sums else None
        cols = ([] if y is None else [y]) + self._pending
        if not cols and self._factor is not None and colsum is None:
            return None
        cols = [np.asarray(c, dtype=float) for c in cols]
        if self._rows is not None:  # the rows are in memory: no read
            out = [RidgeExpectation.__call__(self, c) for c in cols]
            self._done.extend(zip(self._pending, out[len(out) - len(self._pending):],
                                  strict=True))
            self._pending = []
            return out[0] if y is not None else None
        # The products as the in-memory operator forms them (the same bits for one chunk):
        # y^T Phi for one unweighted vector, Phi^T (w y) otherwise.
        gram = np.zeros((d, d)) if self._factor is None else None
        acc = [np.zeros((d,) + c.shape[1:]) for c in cols]
        w = self.weights
        from_gram = colsum is not None and gram is not None and unit
        if from_gram:
            colsum = None
        # Dask arrays: the products are summed on the workers (the column sums as the product
        # with a column of ones); otherwise here, by chunk.
        remote = self.source.remote_products(
            self.h, cols + ([] if colsum is None else [np.ones(self.n_points)]), w,
            gram is not None)
        if remote is not None:
            if gram is not None:
                gram += remote[0]
            if colsum is not None:
                colsum += remote[1].pop()
            for a, r in zip(acc, remote[1], strict=True):
                a += r
        ones = np.ones(0)
        for s, e, rows in (() if remote is not None else self.source.phi_chunks(self.h)):
            if gram is not None:
                xw = rows if w is None else rows * w[s:e, None]
                gram += xw.T @ rows  # a symmetric rank-k update when unweighted
            if colsum is not None:
                if w is None and ones.size < e - s:
                    ones = np.ones(e - s)
                colsum += (ones[: e - s] if w is None else w[s:e]) @ rows
            for a, c in zip(acc, cols, strict=True):
                if w is None and c.ndim == 1:
                    a += c[s:e] @ rows
                elif w is None:
                    a += rows.T @ c[s:e]
                else:
                    a += rows.T @ (c[s:e].T * w[s:e]).T
        self.passes += 1
        self._check_sums([gram, colsum] + acc)
        if from_gram:
            colsum = gram.sum(axis=1)
        if colsum is not None:
            self._sums = colsum
            if w is None:
                self.source.remember_phi_sums(self.h, colsum)
        if gram is not None:
            if w is None:
                self.source.remember_gram(self.h, gram)
            self._factor = _primal_factor(gram, self.gamma, self.weights,
                                          (self.n_points, d))
        out = []
        for a, c in zip(acc, cols, strict=True):
            if w is None and c.ndim == 1:  # Lambda^{-1} = L^{-T} L^{-1}, as in memory
                linv = self._factor.linv
                out.append(linv.T @ (linv @ a))
            else:
                out.append(self._factor.solve(a))
        registered = self._pending
        self._done.extend(zip(registered, out[len(out) - len(registered):], strict=True))
        self._pending = []
        return out[0] if y is not None else None


    def _check_sums(self, sums, rows=None) -> None:
        """Refuse the step's features when a sum formed from them (the Gram matrix, ``Phi^T
        W y``: a NaN or an infinity in a row makes them non-finite) is not finite and the
        features were not checked when the dataset was built; the step's features (``rows``,
        or read again by chunk) are searched only then. The sums' inputs besides the
        features (rewards, values) are checked before they get here."""
        if self._finite:
            return
        if not all(np.isfinite(x).all() for x in sums if x is not None):
            err = self.source.phi_error(self.h, rows)
            if err is not None:
                raise err
            return  # finite features whose sums overflowed: not a data error
        self._finite = any(x is not None for x in sums)


def _primal_factor(gram, gamma, weights, shape) -> GramFactor:
    """The primal factor of ``gram + gamma I`` (``gram`` is modified)."""
    return GramFactor.from_cholesky(_Rows(shape), ridge_cholesky(gram, gamma), weights, gamma)


def _streams(source, form: str, time_homogeneous: bool) -> bool:
    """Whether a step's operator is accumulated by chunk (:class:`ChunkedRidgeExpectation`):
    per-step fits of dense features whose Gram matrix is factored in primal form."""
    if time_homogeneous or not source.dense_rows:  # sparse rows: a step's rows whole
        return False
    if form == "auto":
        form = choose_form(source.n_trajectories, source.n_features)
    return form == "primal"


def _factor(source, h, phi, gamma, sw, form) -> GramFactor:
    """``GramFactor(phi, ...)`` of step ``h``'s rows (the pooled rows: ``h`` None), refusing
    non-finite features a source did not check when it was built: the Cholesky factor of a
    finite Gram matrix is finite, so only a failed or non-finite factor has the rows
    searched."""
    if "phi" in source.checked or not isinstance(phi, np.ndarray):
        return GramFactor(phi, gamma, sw, form)
    try:
        factor = GramFactor(phi, gamma, sw, form)
    except GramMatrixError:
        err = source.phi_error(h, phi)
        if err is not None:
            raise err from None
        raise
    chol = factor.chol if factor.form == "primal" else factor.dual_chol
    if not np.isfinite(chol).all():
        err = source.phi_error(h, phi)
        if err is not None:
            raise err
    return factor


def pooled_steps(horizon: int) -> int:
    """How many steps a time-homogeneous fit pools: ``0 .. H-2``, whose next states are data
    (row ``H-1`` of the next-state data is ignored by every constructor, and files store zeros
    there); the single step when ``H = 1`` (its next states are never used: ``V_H = 0``).

    >>> pooled_steps(20), pooled_steps(1)
    (19, 1)
    """
    return max(int(horizon) - 1, 1)
