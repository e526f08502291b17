"""The one backward-induction loop shared by every algorithm (Algorithms 1-2 of the paper).

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

from ..data import OfflineDataset
from ..data.storage._finite import FIELDS, NonFiniteRows
from ..data.storage.crossed import CrossedRows
from ..duals._scratch import release
from ..duals.gram import GramFactor
from ..duals.operator import ExpectationOperator, RidgeExpectation
from .diagnostics import StepRecorder, known_rows
from .pooled import CrossedRidgeExpectation, PooledNextValues, converged
from .q import FittedModel, _NextValue
from .steps import ChunkedRidgeExpectation, _factor, _streams, pooled_steps

__all__ = ["StepRule", "StepContext", "backward_induction"]


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

    Subclasses implement :meth:`__call__`. ``E`` is the step's expectation operator
    (:class:`~r2pvi.duals.ExpectationOperator`: in a fit the step's ridge estimate, whether
    its rows are held or streamed; any operator works, e.g. the true factors of a known
    model), ``v`` the next-step values at its n points.
    """

    def __call__(self, E: ExpectationOperator, v: np.ndarray, ctx: StepContext) -> np.ndarray:
        """The weights ``w_h (d,)``: the rule's dual under ``E`` at the values ``v (n,)``,
        using only the operator interface."""
        raise NotImplementedError

    def factor_params(self, h: int) -> np.ndarray | None:
        """Per-factor parameters of step h, ``(d,)`` (e.g. radii), or None when the rule
        treats every factor alike. Rules that have them index them by ``ctx.dims``."""
        return None


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
    early_stop: bool = True,
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
    early_stop : bool, default True
        Pooled steps without sample weights: when two consecutive steps' weights agree (to
        ``pooled.STOP_RTOL`` relative) and no learned value reached its step's bound, every
        earlier step would compute the same values and weights (the same operator, the same
        next values), so the fit copies them instead (``FittedModel.diagnostics.stopped_at``).
    """
    H, d = dataset.horizon, dataset.n_features
    # The step-major data (memory, files, Dask arrays, sparse rows, observations): the engine
    # asks the source for a step's rows and products, never which kind it holds.
    source = dataset._source
    nonneg_phi = dataset._nonnegative_phi  # None: checked on a step's features when needed
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
    # V_{h+1} at the sampled next states: kept for per-step fits (H K numbers) and for the
    # variance-aware first pass; a pooled fit's would be H P K numbers (a step's are enough)
    keep_values = not time_homogeneous or value_moments
    next_state_values = np.zeros((H, n_rows) if keep_values else (0, n_rows))
    v_upper = H * r_max
    E = None
    # pooled: V at every next state, with the penalty formed once per factor
    pooled_values = None if pooled is None else PooledNextValues(
        pooled[2], pooled[3], "next" not in checked, source.reward_offset, H,
        dataset.n_trajectories)
    new_factor = True
    stopped_at = None
    # Per-step fits of dense features read a step's features by chunk (ChunkedRidgeExpectation);
    # buffers: one step's (K, d) float64 features, reused when a rule needs them whole.
    chunked = _streams(source, form, time_homogeneous)
    buffers: dict = {}
    step_buffer = None
    # Unchecked data may hold infinities until a step's checks find them: their arithmetic
    # (inf * 0, inf - inf) must not warn first.
    quiet = np.errstate(invalid="ignore", over="ignore") if checked != FIELDS else nullcontext()
    # What the fit can see of its regressions (engine.diagnostics): from the factor and the
    # sums the loop forms anyway.
    recorder = StepRecorder(H, gamma, time_homogeneous, dataset.has_known_values)
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
                    if isinstance(phi, CrossedRows):  # state features: rows never formed
                        E = CrossedRidgeExpectation(phi, gamma, sw, nonneg_phi)
                        factor = E.factor
                    else:
                        factor = _factor(source, None if time_homogeneous else h, phi, gamma,
                                         sw, form)
                        E = RidgeExpectation(phi, factor, sw, nonneg_phi)
                    new_factor = True
                    theta = E(rewards) if reward_weights is None else None
                    inv_diag = None
                if reward_weights is not None:
                    theta = reward_weights[h]
                if h == H - 1:
                    w = np.zeros(d)  # V_H = 0: the robust expectation of 0 is 0 for any divergence
                else:
                    if time_homogeneous:
                        if new_factor:  # the penalty of step h+1's factor, at every next state
                            pooled_values.set_penalty(penalty, beta, inv_diags[h + 1],
                                                      None if ellip is None else ellip[h + 1])
                        new_factor = sw is not None  # the next step's factor, if refactored
                        try:
                            v_next, clipped = pooled_values(weights[h + 1], (H - h - 1) * r_max,
                                                            step=h)
                        except NonFiniteRows as exc:  # pooled rows: step-major
                            step, k = divmod(exc.index[0], dataset.n_trajectories)
                            raise source.next.nonfinite(step, 0, NonFiniteRows(
                                (k,) + exc.index[1:], exc.value, exc.known)) from None
                        if keep_values:
                            next_state_values[h] = v_next
                    else:  # written in place: no K-sized temporary
                        qmax = _NextValue(weights[h + 1], penalty, beta, inv_diags[h + 1],
                                          None if ellip is None else ellip[h + 1],
                                          (H - h - 1) * r_max, check="next" not in checked)
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
                if not time_homogeneous:
                    recorder.record(h, E, factor, sw, known_rows(source.next, h))
                elif h == 0:  # the one pooled regression, after its last use by a rule
                    recorder.record(0, E, factor, sw, next_known)
                elif (early_stop and sw is None and reward_weights is None and h < H - 1
                      and not clipped and not pooled_values.step_dependent
                      and _same_params(rule, h)
                      and converged(weights[h], weights[h + 1])):
                    # a fixed point: steps 0 .. h-1 would see the values of this one
                    weights[:h], thetas[:h], inv_diags[:h] = weights[h], theta, inv_diag
                    if keep_values:
                        next_state_values[:h] = v_next
                    if ellip is not None:
                        ellip[:h] = [step_ellip] * h
                    if value_moments:
                        moments[:h] = moments[h]
                    recorder.record(0, E, factor, sw, next_known)
                    stopped_at = h
                    break
    finally:
        release()  # the duals' reusable work buffers
    report = recorder.report()
    if stopped_at is not None:
        report = replace(report, stopped_at=stopped_at)
    return FittedModel(weights, thetas, inv_diags, ellip, next_state_values,
                       moments if value_moments else None, report)


def _same_params(rule: StepRule, h: int) -> bool:
    """Whether the rule's per-factor parameters of steps ``0 .. h`` are all step ``h``'s."""
    ref = rule.factor_params(h)
    return all(np.array_equal(rule.factor_params(j), ref) if ref is not None
               else rule.factor_params(j) is None for j in range(h))


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

