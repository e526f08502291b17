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

    Nothing of the step's features is held: each request (``E(y)``, or the columns asked for
    together by :meth:`apply_pair`, :meth:`with_total_weights`,
    :meth:`pair_with_total_weights`) reads them once, a chunk at a time
    (``source.phi_chunks``); the first request also forms ``Lambda`` in the same pass, and the
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
            self._pass([])
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
                self._pass([])
            self._total = self._solve_sums(self._sums)
        return self._total.copy()

    def include(self, y: np.ndarray) -> None:
        """Register ``y (n,)`` or ``(n, m)``: its product ``Phi^T W y`` is accumulated with
        the next read of the features, and the next ``E(y)`` of the same array object costs
        no read. The operator keeps ``y`` (so its id cannot be reused by another array) until
        that ``E(y)`` hands out the result and drops it; ``y`` must not be modified in
        between."""
        self._pending.append(y)

    # ------------------------------------------------------------------ the operator
    # Every request goes through _apply: the columns of one request (and E(1)) share one
    # read of the step's features. With the rows in memory, the pair requests take the base
    # class's fused products.
    def __call__(self, y: np.ndarray) -> np.ndarray:
        return self._apply(y)[0]

    def apply_pair(self, y1: np.ndarray, y2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y1), E(y2))`` in one read of the step's features."""
        if self._rows is not None:
            return super().apply_pair(y1, y2)
        return self._apply(y1, y2)

    def with_total_weights(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(E(y), E(1))`` in one read of the step's features (none for ``E(1)`` when the
        column sums are known)."""
        return self._apply(y, total=True)

    def pair_with_total_weights(self, y1: np.ndarray, y2: np.ndarray):
        """``(E(y1), E(y2), E(1))`` in one read of the step's features (``E(1)`` from the
        column sums: known, or accumulated in the same read)."""
        if self._rows is not None:
            return super().pair_with_total_weights(y1, y2)
        return self._apply(y1, y2, total=True)

    def _apply(self, *ys: np.ndarray, total: bool = False) -> tuple[np.ndarray, ...]:
        """``E(y)`` for each ``y`` in ``ys``, then ``E(1)`` when ``total``: one read of the
        step's features (no read with the rows in memory) for the columns not computed yet,
        together with ``Lambda`` when it is not formed, every registered column, and the
        column sums when ``E(1)`` needs them; a registered column's result is handed out
        (and dropped) instead of computed again."""
        if total and self._rows is None:
            self._want_sums = True  # accumulated with the columns if not known
        new = []
        for y in ys:
            if not any(y is c for c in new) and not any(y is p for p in self._pending) and \
                    not any(y is done for done, _ in self._done):
                new.append(y)
        fresh = self._pass(new) if new or any(
            y is p for y in ys for p in self._pending) else []
        out = []
        for k, y in enumerate(ys):
            j = next((j for j in range(k) if ys[j] is y), None)
            i = next((i for i, c in enumerate(new) if c is y), None)
            if j is not None:  # a column asked for twice: its own copy each time
                out.append(out[j].copy())
            else:
                out.append(self._take(y) if i is None else fresh[i])
        if total:
            out.append(self.total_weights())
        return tuple(out)

    def _take(self, y: np.ndarray) -> np.ndarray:
        """The result of the registered column ``y`` (computed by a pass), dropped from the
        operator."""
        i = next(i for i, (done, _) in enumerate(self._done) if done is y)
        return self._done.pop(i)[1]

    def _pass(self, new: list) -> list:
        """One read of the step's features: ``Lambda`` (if not formed yet) and ``Phi^T W y``
        for each column ``y`` of ``new`` and every registered one; returns ``E(y)`` of the
        columns of ``new`` (the registered ones wait in ``_done`` for :meth:`_take`)."""
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
        # chunk; its cost: docs/benchmarks.md).
        colsum = np.zeros(d) if self._sums is None and self._want_sums else None
        cols = list(new) + self._pending
        if not cols and self._factor is not None and colsum is None:
            return []
        cols = [np.asarray(c, dtype=float) for c in cols]
        if self._rows is not None:  # the rows are in memory: no read
            return self._keep([RidgeExpectation.__call__(self, c) for c in cols], len(new))
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
        return self._keep(out, len(new))

    def _keep(self, out: list, n_new: int) -> list:
        """Keep the results of the registered columns (``out[n_new:]``) for :meth:`_take`;
        return the others."""
        self._done.extend(zip(self._pending, out[n_new:], strict=True))
        self._pending = []
        return out[:n_new]

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
    """How many steps a time-homogeneous fit pools: steps ``0`` to ``H-2``, whose next states
    are data (row ``H-1`` of the next-state data is ignored by every constructor, and files
    store zeros there); the single step when ``H = 1`` (its next states are never used:
    ``V_H = 0``).

    >>> pooled_steps(20), pooled_steps(1)
    (19, 1)
    """
    return max(int(horizon) - 1, 1)
