"""What a fit can see of its own regressions, cheaply: rows per step, how much of the data
each feature holds against the ridge, how much a constant target is shrunk (the implicit
discount of the backward induction) and which steps hold an absorbing transition.

The backward induction regresses ``V_{h+1}`` on each step's rows with the ridge operator
``E_h(y) = Lambda_h^{-1} Phi_h^T W y``. When the rows of a step are few for the features, the
operator shrinks every target towards 0: a constant target ``1`` is fitted (on average over
the step's rows) as ``c_h = (Phi^T W 1)^T E_h(1) / sum(W) < 1``, so the values of step ``h``
are those of a discounted problem with discount ``~c`` and horizon ``~1 / (1 - c)``, however
long the task. The recorded facts reuse what the loop computes (the Gram factor, the column
sums ``Phi^T W 1`` that ride along with it); a number that would need another read of a
dataset's files is recorded as None.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["FitDiagnostics", "StarvedFitWarning", "warn_if_starved"]

# The rule of :func:`warn_if_starved`: per-step fits of at least this horizon ...
MIN_HORIZON = 20
# ... whose implicit horizon is below this fraction of H.
HORIZON_FRACTION = 0.25


class StarvedFitWarning(UserWarning):
    """A per-step fit whose regressions cannot learn the task's values: each step holds too
    few rows for its features (a constant target is shrunk to an implicit horizon far below
    ``H``), or most steps hold no absorbing transition that the data holds elsewhere. See
    the estimator's ``fit_report_``."""


@dataclass(frozen=True)
class FitDiagnostics:
    """Facts about a fit's regressions, one entry per regression step.

    A per-step fit has ``H`` entries (step ``h`` at index ``h``); a pooled fit
    (``time_homogeneous=True``) has one, for its one pooled regression. Arrays are None when
    recording them would need another read of the data (a dataset in files).

    Attributes
    ----------
    horizon : int
        ``H``.
    gamma : float
        The ridge parameter.
    pooled : bool
        Whether the steps were pooled (one regression).
    rows : (S,) int or None
        Transitions in each regression: its rows that are not empty (a step after an
        episode's end has an empty row, which adds nothing to a regression).
    feature_mass : (S,) float
        The median over features of ``sum_rows w phi_i^2`` (the Gram diagonal): a feature
        whose mass is small against ``gamma`` is mostly ridge.
    starved_features : (S,) float
        The fraction of features whose mass ``sum_rows w phi_i^2`` is below ``gamma``.
    constant_fit : (S,) float or None
        The fitted value of the constant target 1, averaged over the regression's
        transitions: ``(Phi^T W 1)^T Lambda^{-1} (Phi^T W 1) / sum(W)``, the sum over the
        non-empty rows (1 without shrinkage; NaN for a regression without transitions).
    absorbing : (S,) int or None
        Rows with a known next-state value (e.g. 0 after a failure) in each regression
        (a per-step fit's step ``H-1`` included, though its next values never enter the
        fit); None when the known values are not in memory.
    has_absorbing : bool
        Whether the dataset gives any known next-state value.
    stopped_at : int or None
        A pooled fit that reached a fixed point: the step from which the weights stopped
        changing (every earlier step holds that step's weights); None otherwise.
    """

    horizon: int
    gamma: float
    pooled: bool
    rows: np.ndarray | None
    feature_mass: np.ndarray
    starved_features: np.ndarray
    constant_fit: np.ndarray | None
    absorbing: np.ndarray | None
    has_absorbing: bool
    stopped_at: int | None = None

    @property
    def implicit_discount(self) -> float | None:
        """The median of :attr:`constant_fit` over the regressions with transitions, or
        None."""
        if self.constant_fit is None or np.isnan(self.constant_fit).all():
            return None
        return float(np.nanmedian(self.constant_fit))

    @property
    def implicit_horizon(self) -> float | None:
        """``1 / (1 - implicit_discount)``: how many steps of reward a value can hold before
        the ridge shrinks it away (inf without shrinkage), or None."""
        c = self.implicit_discount
        if c is None:
            return None
        return float("inf") if c >= 1.0 else 1.0 / (1.0 - c)

    def _used_absorbing(self) -> np.ndarray | None:
        """:attr:`absorbing` of the regressions whose next values enter the fit: a per-step
        fit's step ``H-1`` regresses ``V_H = 0`` whatever its next states."""
        if self.absorbing is None:
            return None
        return self.absorbing if self.pooled or self.horizon == 1 else self.absorbing[:-1]

    @property
    def steps_without_absorbing(self) -> int | None:
        """How many regressions whose next values enter the fit (a per-step fit's steps
        ``0`` to ``H-2``; the pooled one) hold no row with a known next-state value, or None."""
        used = self._used_absorbing()
        return None if used is None else int(np.count_nonzero(used == 0))

    def starved(self) -> list[str]:
        """Why a per-step fit cannot learn, one sentence a reason (empty: no reason).

        A pooled fit, or one with ``H < 20``, is never said starved: the rule fires when the
        implicit horizon is below ``H / 4``, or when more than half of the steps hold no
        absorbing transition while the dataset holds some."""
        if self.pooled or self.horizon < MIN_HORIZON:
            return []
        reasons = []
        ih = self.implicit_horizon
        if ih is not None and ih < HORIZON_FRACTION * self.horizon:
            reasons.append(
                f"each step's ridge regression fits a constant target as "
                f"{self.implicit_discount:.3g} (median over steps): an implicit horizon of "
                f"{ih:.3g} steps against H = {self.horizon}")
        used = self._used_absorbing()
        if used is not None and used.sum() > 0 and np.count_nonzero(used == 0) > used.size / 2:
            reasons.append(
                f"{np.count_nonzero(used == 0)} of {used.size} steps hold no absorbing "
                "transition (a known next-state value) while the data holds some, so those "
                "steps cannot learn which actions lead to one")
        return reasons

    def summary(self) -> str:
        """A few lines: the regressions' rows, feature mass, shrinkage and absorbing steps."""
        kind = ("pooled (one regression)" if self.pooled
                else f"per-step ({self.horizon} regressions)")
        lines = [f"fit: {kind}, H = {self.horizon}, gamma = {self.gamma:g}",
                 "  transitions per regression: " + (
                     "not recorded (would need another read of the data)" if self.rows is None
                     else f"median {np.median(self.rows):g}, min {np.min(self.rows)}"),
                 f"  feature mass sum(phi_i^2): median {np.median(self.feature_mass):.3g} "
                 f"(gamma {self.gamma:g}); features below gamma: "
                 f"{100 * np.median(self.starved_features):.0f}%"]
        if self.implicit_discount is None:
            lines.append("  constant-target fit: not recorded (would need another read of "
                         "the data)")
        else:
            ih = self.implicit_horizon
            lines.append(
                f"  constant-target fit (implicit discount): median "
                f"{self.implicit_discount:.3g}, min {np.nanmin(self.constant_fit):.3g}; implicit "
                f"horizon {ih:.3g} steps")
        if self.absorbing is None:
            lines.append("  absorbing transitions: not recorded (known values not in memory)")
        elif not self.has_absorbing:
            lines.append("  absorbing transitions: none in the dataset")
        else:
            lines.append(
                f"  absorbing transitions: {int(self._used_absorbing().sum())} rows; "
                f"regressions without one: {self.steps_without_absorbing} of "
                f"{self._used_absorbing().size}")
        if self.stopped_at is not None:
            lines.append(f"  fixed point: the weights stopped changing at step "
                         f"{self.stopped_at}; steps 0 .. {self.stopped_at - 1} hold its weights")
        for reason in self.starved():
            lines.append("  STARVED: " + reason)
        return "\n".join(lines)


def warn_if_starved(report: FitDiagnostics | None, stacklevel: int = 3) -> None:
    """Warn (:class:`StarvedFitWarning`) with the fix when :meth:`FitDiagnostics.starved`
    finds a reason."""
    if report is None:
        return
    reasons = report.starved()
    if not reasons:
        return
    warnings.warn(
        "the per-step fit starves: " + "; ".join(reasons) + ". Fix: for a stationary task "
        "pool the steps (time_homogeneous=True: one regression over every transition); "
        "otherwise use fewer features or a smaller gamma. See the estimator's fit_report_.",
        StarvedFitWarning, stacklevel=stacklevel)


class StepRecorder:
    """Collects the facts of each regression as the backward induction runs."""

    def __init__(self, horizon: int, gamma: float, pooled: bool, has_absorbing: bool):
        n = 1 if pooled else horizon
        self.horizon, self.gamma, self.pooled = horizon, gamma, pooled
        self.has_absorbing = has_absorbing
        self.rows = np.zeros(n)
        self.diag = [None] * n
        self.const = np.full(n, np.nan)
        self.absorbing = np.zeros(n, dtype=np.int64)
        self.absorbing_known = True
        self.const_known = True

    def record(self, i: int, E, factor, weights, known) -> None:
        """Regression ``i``: its operator ``E`` (a held or chunked ridge operator), its
        factor (None: the chunked operator's), its row weights and its known next values
        (``(n, A)``; None: none given; ``False``: not in memory)."""
        diag, sums, used, total = _gram_diagonal_and_sums(E, factor, weights)
        self.rows[i] = np.nan if used is None else used
        self.diag[i] = diag
        if sums is None or total is None:
            self.const_known = False
        elif total > 0:  # no transition: NaN
            # E(1) = Lambda^{-1} Phi^T W 1, solved as the operator solves (its cache untouched);
            # the mean of the fitted constant over the transitions
            self.const[i] = float(sums @ E._solve_sums(sums)) / total
        if known is False:
            self.absorbing_known = False
        elif known is not None:
            self.absorbing[i] = int(np.count_nonzero(~np.isnan(known).all(axis=1)))

    def report(self) -> FitDiagnostics:
        rows = None if np.isnan(self.rows).any() else self.rows.astype(np.int64)
        diag = np.array(self.diag)  # (S, d): the medians of every step at once
        return FitDiagnostics(
            self.horizon, self.gamma, self.pooled, rows, np.median(diag, axis=1),
            np.mean(diag < self.gamma, axis=1),
            self.const if self.const_known else None,
            self.absorbing if self.absorbing_known else None, self.has_absorbing)


def _gram_diagonal_and_sums(E, factor, weights):
    """``(diag(Phi^T W Phi), Phi^T W 1, non-empty rows, their total weight)`` of a
    regression, from what the fit holds: the primal Cholesky factor and the column sums a
    chunked operator kept (or, for rows summing to 1, ``Phi^T W Phi 1`` from the factor); the
    rows when they are in memory. None for a number that would need another read of the data
    (files, Dask arrays). Empty rows (steps after an episode's end) are no transitions. The
    operator's state is not changed."""
    if factor is None:  # chunked: the primal factor and the sums that rode along with it
        return _chunked_diagonal_and_sums(E, weights)
    own = getattr(E, "gram_diagonal_and_sums", None)
    if own is not None:  # rows the operator never forms (state features)
        return own()
    phi = E.phi
    w = np.ones(phi.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    if sp.issparse(phi):
        phi = sp.csr_matrix(phi)
        diag = np.asarray(phi.multiply(phi).T @ w).ravel()
        sums = np.asarray(phi.T @ w).ravel()
        used = phi.getnnz(axis=1) > 0
    else:
        diag = np.einsum("ij,ij,i->j", phi, phi, w)
        sums = w @ phi
        used = _non_empty(phi, E.nonnegative_features)
    return (diag, sums) + _transitions(used, weights)


def _non_empty(rows: np.ndarray, nonnegative) -> np.ndarray:
    """Which dense rows hold a non-zero feature: a non-zero row sum (one product), and for
    the rows summing to 0 (empty ones, or signed features that cancel) a look at them."""
    used = rows @ np.ones(rows.shape[1]) != 0
    if not nonnegative:
        zero = np.flatnonzero(~used)
        if zero.size:
            used[zero] = rows[zero].any(axis=1)
    return used


def _transitions(used: np.ndarray, weights) -> tuple[int, float]:
    """The count of non-empty rows and their total weight."""
    count = int(np.count_nonzero(used))
    return count, float(count) if weights is None else float(weights[used].sum())


def _chunked_diagonal_and_sums(E, weights):
    chol = E.factor.chol  # Lambda = L L^T = Phi^T W Phi + gamma I
    diag = np.einsum("ij,ij->i", chol, chol) - E.gamma
    source = E.source
    n = E.n_points
    sums = E._sums
    if sums is None and weights is None:
        sums = source.phi_sums(E.h)  # stored with the data, or kept from an earlier fit
    if sums is None and source.unit_rows:  # Phi^T W 1 = Phi^T W Phi 1_d
        sums = chol @ (chol.T @ np.ones(chol.shape[0])) - E.gamma
    row_sums = source.phi_row_sums
    if source.unit_rows or (row_sums is not None and row_sums[0] > 0):  # no empty row
        return diag, sums, n, float(n) if weights is None else float(np.sum(weights))
    crossed = getattr(source.phi, "crossed_step", None)  # state features held in memory
    if crossed is not None:
        rows = crossed(E.h)
        if sums is None:
            sums = rows.colsums(weights)
        return (diag, sums) + _transitions(rows.used(), weights)
    held = source.phi.float64_array()  # the rows when held in memory, else None
    if held is not None:
        rows = held[E.h]
        if sums is None:
            sums = (np.ones(n) if weights is None else weights) @ rows
        return (diag, sums) + _transitions(_non_empty(rows, E.nonnegative_features), weights)
    return diag, sums, None, None


def known_rows(next_form, h: int):
    """Step ``h``'s known next values ``(n, A)`` when held in memory, None when the dataset
    gives none, False when reading them would be another read of the data (files)."""
    if not next_form.has_known_values:
        return None
    table = getattr(next_form, "known_table", None)
    field = getattr(next_form, "next_values", getattr(next_form, "known_values", None))
    held = getattr(field, "float64_array", None)
    if table is None and (held is None or held() is None):  # not held in memory
        return False
    return next_form.known(h)
