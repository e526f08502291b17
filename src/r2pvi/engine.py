"""The one backward-induction engine shared by every algorithm (Algorithms 1-2 of the paper).

**Steps are 0-based in code**: the paper's step ``h = 1..H`` is ``h = 0..H-1`` here, so the
paper's clipping ``min{., H - h + 1}^+`` reads ``clip(., 0, (H - h) * r_max)``.

For ``h = H-1, ..., 0`` the engine

1. factors the Gram matrix ``Lambda_h = sum_tau w_tau phi_tau phi_tau^T + gamma I`` in primal
   (d x d) or dual (K x K, Woodbury) form, whichever is cheaper (no explicit inverse), for
   dense or ``scipy.sparse`` features (:class:`~r2pvi.duals.GramFactor`);
2. computes the next-step values ``V_{h+1}(s') = max_a Q_{h+1}(s', a)`` at the sampled next
   states, taking known action values where the dataset gives them (``V_H = 0``);
3. asks the algorithm's :class:`StepRule` for the weights ``w_h`` — the only thing that
   differs between algorithms; at ``h = H-1`` the next values are identically 0 and
   ``w_{H-1} = 0`` for every divergence, so the rule is not called;
4. stores ``theta_h + w_h`` and what the penalty ``Gamma_h`` needs, which define
   ``Q_h = clip(phi^T (theta_h + w_h) - Gamma_h(phi), 0, (H - h) r_max)``.

With ``time_homogeneous=True`` (pooled steps) every step regresses on the transitions of
steps ``0 .. H-2`` (all of them when ``H = 1``) with one Gram matrix factored once: the last
step's next states are not part of a dataset (every constructor documents that row ``H-1`` of
the next-state data is ignored; files store zeros there), so they never enter a fit.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from .data import OfflineDataset
from .data.storage._finite import FIELDS, NonFiniteRows, check_next_products
from .data.storage.sparse_rows import flat_rows
from .duals._scratch import release
from .duals.gram import GramFactor, GramMatrixError, choose_form, ridge_cholesky
from .duals.operator import RidgeExpectation

__all__ = [
    "StepRule",
    "StepContext",
    "ChunkedRidgeExpectation",
    "FittedModel",
    "backward_induction",
    "penalty_values",
    "elliptical_norms",
    "q_values_from_model",
    "pooled_steps",
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
    # The factors (features) the operator's rows stand for, when the engine hands the rule an
    # operator restricted to some of them (sparse rows with unused features); None: all d.
    dims: np.ndarray | None = None

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

    def factor_params(self, h: int) -> np.ndarray | None:
        """Per-factor parameters of step h, ``(d,)`` (e.g. radii), or None when the rule
        treats every factor alike. Rules that have them index them by ``ctx.dims``."""
        return None


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
    next_state_values : (H, n) ``V_{h+1}`` at the sampled next states (0 at ``h = H-1``)
    value_moments : (H, d, 2) ``E_h([U, U^2])``, ``U = V_{h+1} / r_max``: the ridge estimates
        of the first two moments of the next-step value, in units of ``r_max`` (finite for any
        finite ``r_max``), under step h's operator (variance-aware variants)
    """

    weights: np.ndarray
    reward_weights: np.ndarray
    gram_inv_diag: np.ndarray
    elliptical: list | None = None
    next_state_values: np.ndarray | None = None
    value_moments: np.ndarray | None = None


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
        if nonneg:  # |phi| = phi: one matrix-vector product (an n x 2 GEMM costs ~3x one)
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
        self.weights = weights
        self.nonnegative_features = nonnegative_features
        self.n_points, self.n_dims = source.n_trajectories, source.n_features
        self.primal_dense = True
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
        if getattr(self, "_total", None) is None:
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
    time_homogeneous: bool = False,
    form: str = "auto",
    value_moments: bool = False,
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
    sample_weights : (H, n), optional
        Regression weights ``1 / sigma_h^2`` (variance-aware variants); None means 1.
        ``n`` is K, or ``pooled_steps(H) K`` with ``time_homogeneous``.
    time_homogeneous : bool, default False
        Pooled steps: every step regresses on the transitions of steps ``0 .. H-2``
        (:func:`pooled_steps`; the last step's next states are not data), with ONE Gram
        matrix ``Lambda = sum_{h, tau} phi phi^T + gamma I`` factored once (once per step
        only when ``sample_weights`` differ by step); each step then computes only its
        next-state values at the pooled next states and its regressions. Valid when the
        nominal dynamics (and rewards) do not depend on h.
    form : {"auto", "primal", "dual"}
        Factorization of each Gram matrix (see :class:`~r2pvi.duals.GramFactor`); "auto"
        takes the cheaper from the shapes.
    value_moments : bool, default False
        Also store ``E_h([U, U^2])``, ``U = V_{h+1} / r_max`` (``FittedModel.value_moments``),
        which the variance-aware variants' first pass needs; two more regressions per step.
    """
    H, d = dataset.horizon, dataset.n_features
    # The step-major data (memory, files, Dask arrays, sparse rows, observations): the engine
    # asks the source for a step's rows and products, never which kind it holds.
    source = dataset._source
    nonneg_phi = dataset._nonnegative_phi  # None: checked on a step's features when needed
    nonneg = dataset.nonnegative_next_features if time_homogeneous else None
    weights = np.zeros((H, d))
    thetas = np.zeros((H, d))
    inv_diags = np.zeros((H, d))
    ellip = [None] * H if penalty == "elliptical" else None
    moments = np.zeros((H, d, 2))
    # ---- data access: one step's arrays, or every step's pooled (the only data path here)
    pooled = source.pooled(pooled_steps(H)) if time_homogeneous else None
    # What the dataset did not check when it was built (files, Dask arrays, feature maps) is
    # checked as the fit reads it: see data.storage._finite.
    checked = source.checked
    if pooled is not None and reward_weights is None and "rewards" not in checked:
        K = dataset.n_trajectories
        for h in range(pooled_steps(H)):
            source.check_rewards(h, pooled[1][h * K:(h + 1) * K], r_max)
    n_rows = dataset.n_trajectories * (pooled_steps(H) if time_homogeneous else 1)
    next_state_values = np.zeros((H, n_rows))
    v_upper = H * r_max
    E = None
    # Per-step fits of dense features read a step's features by chunk (ChunkedRidgeExpectation);
    # buffers: one step's (K, d) float64 features, reused when a rule needs them whole.
    chunked = _streams(source, form, time_homogeneous)
    buffers: dict = {}
    step_buffer = None
    # Unchecked data may hold infinities until a step's checks find them: their arithmetic
    # (inf * 0, inf - inf) must not warn first.
    quiet = np.errstate(invalid="ignore", over="ignore") if checked != FIELDS else nullcontext()
    try:
        with quiet:
            for h in range(H - 1, -1, -1):
                if time_homogeneous:
                    phi, rewards, next_phi, next_known = pooled
                else:  # next-state data: by chunk; the rewards only when theta is estimated
                    rewards = source.rewards_step(h) if reward_weights is None else None
                    if rewards is not None:
                        source.check_rewards(h, rewards, r_max)
                    if not chunked:
                        phi = step_buffer = source.phi_step(h, step_buffer)
                sw = None if sample_weights is None else sample_weights[h]
                # ---- linear algebra: the step's factor (pooled and unweighted: factored once)
                if chunked:
                    # Lambda and every regression of the step in as few reads as possible: the
                    # rewards (and moments) ride along with the first pass.
                    E = ChunkedRidgeExpectation(source, h, gamma, sw, nonneg_phi, buffers)
                    factor = None
                    if reward_weights is None:
                        E.include(rewards)
                    theta = None
                    inv_diag = None
                elif E is None or not time_homogeneous or sw is not None:
                    factor = _factor(source, None if time_homogeneous else h, phi, gamma, sw, form)
                    E = RidgeExpectation(phi, factor, sw, nonneg_phi)
                    theta = E(rewards) if reward_weights is None else None
                    inv_diag = None
                if reward_weights is not None:
                    theta = reward_weights[h]
                if h == H - 1:
                    w = np.zeros(d)  # V_H = 0: the robust expectation of 0 is 0 for any divergence
                else:
                    qmax = _NextValue(weights[h + 1], penalty, beta, inv_diags[h + 1],
                                      None if ellip is None else ellip[h + 1], (H - h - 1) * r_max,
                                      check="next" not in checked)
                    if time_homogeneous:
                        try:
                            v_next = qmax(next_phi, next_known, nonneg)
                        except NonFiniteRows as exc:  # pooled rows: step-major
                            step, k = divmod(exc.index[0], dataset.n_trajectories)
                            raise source.next.nonfinite(step, 0, NonFiniteRows(
                                (k,) + exc.index[1:], exc.value, exc.known)) from None
                        next_state_values[h] = v_next
                    else:  # written in place: no K-sized temporary
                        v_next = source.next_state_values(h, qmax, out=next_state_values[h])
                    if value_moments:  # only the variance-aware variants need them
                        unit_v = v_next / r_max  # in units of r_max: U^2 never overflows
                        if chunked:
                            both = np.stack([unit_v, unit_v * unit_v], axis=1)
                            E.include(both)
                        else:
                            moments[h] = np.stack([E(unit_v), E(unit_v * unit_v)], axis=1)
                    w = _apply_rule(rule, E, factor, v_next, StepContext(h, H, r_max, v_upper))
                    if value_moments and chunked:
                        moments[h] = E(both)
                if theta is None:  # a chunked step: after the rule, whose first pass computed it
                    theta = E(rewards)
                if inv_diag is None:  # after the rule: reuses what the rule formed (dual form)
                    inv_diag = E.inverse_diagonal()
                    step_ellip = (E.factor if factor is None else factor).elliptical_factor() \
                        if ellip is not None else None
                weights[h] = theta + w
                thetas[h] = theta
                inv_diags[h] = inv_diag
                if ellip is not None:
                    ellip[h] = step_ellip
    finally:
        release()  # the duals' reusable work buffers
    return FittedModel(weights, thetas, inv_diags, ellip, next_state_values,
                       moments if value_moments else None)


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


def _apply_rule(rule: StepRule, E: RidgeExpectation, factor: GramFactor, v, ctx: StepContext):
    """``rule(E, v, ctx)``; with sparse rows that leave features unused, on the operator
    restricted to the used features plus one unused representative per distinct value of the
    rule's per-factor parameters. An unused feature has a zero weight row, so its dual value
    is that of its representative: the same numbers, with the duals' O(n d) work on the used
    features only."""
    if factor is None:  # a chunked operator: dense rows, primal form
        return rule(E, v, ctx)
    active = factor.active_features()
    d = E.n_dims
    if active is None or active.size > 0.75 * d:
        return rule(E, v, ctx)
    unused = np.setdiff1d(np.arange(d), active, assume_unique=True)
    params = rule.factor_params(ctx.h)
    if params is None:
        reps, group = unused[:1], np.zeros(unused.size, dtype=np.intp)
    else:
        _, first, group = np.unique(np.asarray(params)[unused], return_index=True,
                                    return_inverse=True)
        reps = unused[first]
    cols = np.concatenate([active, reps])
    sub = RidgeExpectation(E.phi[:, cols], factor.restrict(cols), E.weights,
                           E.nonnegative_features)
    w_sub = rule(sub, v, replace(ctx, dims=cols))
    w = np.empty(d)
    w[cols] = w_sub
    w[unused] = w_sub[active.size + group.ravel()]
    return w


def pooled_steps(horizon: int) -> int:
    """How many steps a time-homogeneous fit pools: ``0 .. H-2``, whose next states are data
    (row ``H-1`` of the next-state data is ignored by every constructor, and files store zeros
    there); the single step when ``H = 1`` (its next states are never used: ``V_H = 0``).

    >>> pooled_steps(20), pooled_steps(1)
    (19, 1)
    """
    return max(int(horizon) - 1, 1)
