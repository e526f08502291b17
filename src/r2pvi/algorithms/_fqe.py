"""Fitted-Q evaluation of a fitted estimator's greedy policy on held-out trajectories.

The value of the policy ``pi_h(s) = argmax_a Q_h(s, a)`` the estimator acts with (its own
``Q``: penalty and clip included) is estimated from the held-out data alone, backward over
the steps: ``V^pi_H = 0`` and, for ``h = H-1, ..., 0``,

    Q^pi_h(s, a) = clip(phi(s, a)^T (theta_h + w_h), 0, (H - h) r_max),
    v = Q^pi_{h+1}(s', pi_{h+1}(s'))    at the held-out next states s'
                                        (known next-state values where the data gives them),

with ``theta_h`` the ridge regression of the rewards and ``w_h``

- ``E(v)``, the ridge regression of ``v`` (``robust=False``): the **nominal** value of
  ``pi`` under the held-out data's dynamics;
- ``rule(E, v)``, the estimator's own step rule (:meth:`LinearEstimator._make_rule`) applied
  to the held-out ridge operator, as the fit applies it to the training one (``robust=True``):
  the **robust (regularized or constrained) value** of ``pi`` under the estimator's
  uncertainty model around the held-out data's dynamics. For PEVI (no uncertainty set) the
  rule is a ridge regression kept in the values' range: the nominal value again.

``E`` is one ridge operator (``gamma``: the estimator's unless given) over every held-out
transition of
steps ``0 .. H-2`` when the steps are pooled (stationary data: as a pooled fit), or step
``h``'s transitions alone per step (the paper's form). No pessimism penalty enters ``Q^pi``:
it is an evaluation, not a lower bound.
"""

from __future__ import annotations

import numpy as np

from ..data import OfflineDataset
from ..data.storage.crossed import CrossedRows, cross_rows
from ..data.storage.sparse_rows import flat_rows
from ..duals import GramFactor
from ..duals.operator import RidgeExpectation
from ..engine import StepContext, pooled_steps
from ..engine.pooled import CrossedRidgeExpectation, converged, next_penalty
from ..features.maps import as_feature_map

__all__ = ["policy_value", "check_evaluation_dataset", "evaluation_features"]


def _action_values(feats, w: np.ndarray) -> np.ndarray:
    """``phi(s', a)^T w`` at every next state and action ``(n, A)``."""
    if isinstance(feats, CrossedRows):
        return feats.action_values(w)
    flat, lead = flat_rows(feats)
    return np.asarray(flat @ w).reshape(lead)


def _penalty_values(feats, kind: str, beta: float, inv_diag, ellip) -> np.ndarray:
    """The estimator's penalty ``Gamma(phi(s', a))`` at every next state and action
    ``(n, A)``; for crossed rows ``e_a (x) psi`` from ``psi`` and action ``a``'s block of the
    fitted factor (``A`` times fewer products than the dense rows), else as the engine forms
    it (:func:`~r2pvi.engine.pooled.next_penalty`)."""
    r = None if ellip is None else ellip[0]
    if not isinstance(feats, CrossedRows) or (kind == "elliptical"
                                              and not isinstance(r, np.ndarray)):
        return next_penalty(feats, kind, beta, inv_diag, ellip)
    A, m = feats.n_actions, feats.m
    out = np.empty((feats.n, A))
    for s, e, psi in feats.chunks():
        for a in range(A):
            blk = slice(a * m, (a + 1) * m)
            if kind == "l1":
                out[s:e, a] = np.abs(psi) @ np.sqrt(inv_diag[blk])
            elif kind == "l2":
                out[s:e, a] = np.sqrt((psi * psi) @ inv_diag[blk])
            else:  # ||x||^2_{Lambda^-1} = c0 ||x||^2 + c1 ||R x||^2 (engine.penalty)
                _, c0, c1 = ellip
                rx = psi @ r[:, blk].T
                sq = c1 * np.einsum("ij,ij->i", rx, rx)
                if c0:
                    sq += c0 * np.einsum("ij,ij->i", psi, psi)
                out[s:e, a] = np.sqrt(np.maximum(sq, 0.0))
    return beta * out


def _operator(phi, gamma: float, nonneg) -> RidgeExpectation:
    """The ridge operator of held-out rows (crossed state features: never formed)."""
    if isinstance(phi, CrossedRows):
        return CrossedRidgeExpectation(phi, gamma, None, nonneg)
    return RidgeExpectation(phi, GramFactor(phi, gamma), None, nonneg)


class _Rows:
    """The held-out regressions: one pooled set of rows, or each step's own.

    With an ``evaluation_map`` (pooled only) the regressions use its features of the same
    observations (``dataset.states`` and ``dataset.next_states``), while the policy acts on
    the dataset's own next-state rows (:attr:`policy_feats`)."""

    def __init__(self, dataset: OfflineDataset, gamma: float, pooled: bool,
                 evaluation_map=None):
        self.dataset, self.gamma, self.pooled = dataset, float(gamma), pooled
        self.H, self.K = dataset.horizon, dataset.n_trajectories
        self.offset = float(dataset._source.reward_offset)
        self.nonneg = dataset._nonnegative_phi
        self.x0 = None  # the evaluation map's initial features, when there is one
        if pooled:
            phi, rewards, self.feats, known = dataset._source.pooled(pooled_steps(self.H))
            self.policy_feats = self.feats
            if evaluation_map is not None:
                phi, self.feats, self.x0 = _evaluation_rows(dataset, evaluation_map)
                self.nonneg = None
            self.E = _operator(phi, gamma, self.nonneg)
            self.theta = self.E(np.asarray(rewards, dtype=np.float64))
            self.rows, self.row_known = None, None
            if known is not None:  # the rows with a known value (absorbing states): few
                self.rows = np.flatnonzero(~np.isnan(known).all(axis=1))
                # without the shift still to come after the row's own step (engine.pooled)
                steps = self.rows // self.K
                self.row_known = known[self.rows] - ((self.H - steps - 1)
                                                     * self.offset)[:, None]

    @property
    def step_dependent(self) -> bool:
        """Whether pooled known values change with the step (shifted rewards)."""
        return bool(self.offset) and self.rows is not None and self.rows.size > 0

    def step(self, h: int):
        """``(E, theta, policy rows, value rows, known, rows id)`` of step ``h``'s
        regression: the next-state rows the policy acts on and those the values are read
        from (the same unless an evaluation map is given); ``known`` is ``(rows, values
        (n_rows, A))`` of the rows with a known next value, or None; ``rows id`` names the
        next-state rows (the same for every pooled step)."""
        if self.pooled:
            known = None
            if self.rows is not None and self.rows.size:
                known = (self.rows, self.row_known + (self.H - h - 1) * self.offset)
            return self.E, self.theta, self.policy_feats, self.feats, known, -1
        phi, r, nphi, known = self.dataset.step(h)
        E = _operator(phi, self.gamma, self.nonneg)
        if known is not None:
            rows = np.flatnonzero(~np.isnan(known).all(axis=1))
            known = (rows, known[rows]) if rows.size else None
        return E, E(np.asarray(r, dtype=np.float64)), nphi, nphi, known, h


def check_evaluation_dataset(dataset: OfflineDataset) -> None:
    """Refuse a dataset an evaluation map cannot read (see :func:`_evaluation_rows`)."""
    if not hasattr(dataset._source.phi, "crossed_step") or dataset.states is None:
        raise ValueError(
            "evaluation_map needs a dataset of episodes built with a feature map crossed with "
            "the actions (OfflineDataset.from_episodes(episodes, cross_actions(map, A), A)): "
            "it reads the observations and the taken actions of every step")


def evaluation_features(dataset: OfflineDataset, evaluation_map):
    """``(psi of the states, psi of the next states)``, each ``(H, K, m)`` step-major: the
    state features of ``evaluation_map`` (a fitted observation transformer, or a map crossed
    with the dataset's actions) at the observations of a dataset of episodes."""
    A = dataset.n_actions
    emap = as_feature_map(evaluation_map, A)
    if getattr(emap, "n_actions", A) != A:
        raise ValueError(f"evaluation_map is crossed with {emap.n_actions} actions; the dataset "
                         f"has A = {A}")
    if not hasattr(emap, "state_features"):
        raise TypeError("evaluation_map must be a fitted observation transformer or a map "
                        "crossed with the actions (r2pvi.features.cross_actions), got "
                        f"{type(evaluation_map).__name__}")

    def psi(obs):  # (K, H, ...) -> (H, K, m)
        obs = np.swapaxes(np.asarray(obs), 0, 1)
        out = emap.state_features(obs.reshape((-1,) + obs.shape[2:]))
        out = np.asarray(out.toarray() if hasattr(out, "toarray") else out, dtype=np.float64)
        return out.reshape(obs.shape[0], obs.shape[1], -1)

    return psi(dataset.states), psi(dataset.next_states)


def _evaluation_rows(dataset: OfflineDataset, evaluation_map):
    """``(taken rows, next rows, initial features (K, A, d'))`` of the pooled steps under
    ``evaluation_map``, from the observations of a dataset of episodes stored as state
    features (its taken actions, ``-1`` after an episode's end, give the empty rows)."""
    check_evaluation_dataset(dataset)
    A, H, K = dataset.n_actions, dataset.horizon, dataset.n_trajectories
    states, next_states = evaluation_features(dataset, evaluation_map)
    P = pooled_steps(H)
    actions = np.asarray(dataset._source.phi.actions[:P]).reshape(P * K)
    taken = CrossedRows(states[:P].reshape(P * K, -1), actions, A)
    nxt = CrossedRows(next_states[:P].reshape(P * K, -1), None, A)
    return taken, nxt, cross_rows(states[0], None, A)


class _Policy:
    """The estimator's greedy actions at the next states of the held-out rows, step by
    step; its penalty is formed once per distinct fitted factor (every step of a pooled
    fit shares one)."""

    def __init__(self, est):
        self.est = est
        fp = est._fit_params
        self.kind, self.beta, self.r_max = fp["penalty"], float(fp["beta"]), fp["r_max"]
        self.H = est.horizon_
        self._pen_key = None
        self._pen = None

    def _penalty(self, feats, j: int, feats_id):
        if self.beta == 0.0:
            return None
        est = self.est
        ellip = None if getattr(est, "_elliptical", None) is None else est._elliptical[j]
        inv_diag = est.gram_inv_diag_[j]
        key = self._pen_key
        same = key is not None and key[0] == feats_id and (
            key[1] is ellip if self.kind == "elliptical" else np.array_equal(key[2], inv_diag))
        if not same:
            self._pen = _penalty_values(feats, self.kind, self.beta, inv_diag, ellip)
            self._pen_key = (feats_id, ellip, inv_diag)
        return self._pen

    def same(self, j: int, k: int) -> bool:
        """Whether steps ``j`` and ``k`` act alike (the same weights and penalty)."""
        est = self.est
        if not np.array_equal(est.weights_[j], est.weights_[k]):
            return False
        if self.beta == 0.0:
            return True
        if self.kind == "elliptical":
            return est._elliptical[j] is est._elliptical[k]
        return np.array_equal(est.gram_inv_diag_[j], est.gram_inv_diag_[k])

    def actions(self, feats, j: int, known, feats_id) -> np.ndarray:
        """``argmax_a Q_j(s', a)`` as the estimator acts (clip and known values included;
        ties to the lowest index)."""
        q = _action_values(feats, self.est.weights_[j])
        pen = self._penalty(feats, j, feats_id)
        if pen is not None:
            q -= pen
        np.clip(q, 0.0, (self.H - j) * self.r_max, out=q)
        if known is not None:
            rows, values = known
            q[rows] = np.where(np.isnan(values), q[rows], values)
        return np.argmax(q, axis=1)


def policy_value(est, dataset: OfflineDataset, x0: np.ndarray, *, robust: bool,
                 pooled: bool, gamma: float | None = None, evaluation_map=None) -> float:
    """The mean initial-state value of ``est``'s greedy policy by fitted-Q evaluation on
    ``dataset`` (see the module docstring): ``mean_i Q^pi_0(s_i, pi_0(s_i))`` over the
    initial features ``x0 (n, A, d)``; ``gamma`` is the evaluation's ridge parameter (None:
    the estimator's); ``evaluation_map`` (pooled, nominal) regresses on its own features."""
    H = dataset.horizon
    r_max = float(est._fit_params["r_max"])
    rows = _Rows(dataset, est.gamma if gamma is None else gamma, pooled, evaluation_map)
    policy = _Policy(est)
    rule = None
    if robust:
        params = est._validate_common(dataset)
        params.update(est._validate_extra(dataset))
        rule = est._make_rule(params)
    w_next = None
    for h in range(H - 1, -1, -1):
        E, theta, policy_feats, feats, known, feats_id = rows.step(h)
        if h == H - 1:
            w = np.zeros_like(theta)  # V_H = 0: every rule's value of 0 is 0
            clipped = True
        else:
            upper = (H - h - 1) * r_max
            act = policy.actions(policy_feats, h + 1, known, feats_id)
            n = act.shape[0]
            v = _action_values(feats, w_next)[np.arange(n), act]
            clipped = bool(v.max(initial=-np.inf) >= upper)
            np.clip(v, 0.0, upper, out=v)
            if known is not None:
                k_rows, k_values = known
                kv = k_values[np.arange(k_rows.size), act[k_rows]]
                v[k_rows] = np.where(np.isnan(kv), v[k_rows], kv)
            if rule is None:
                w = E(v)
            else:
                w = rule(E, v, StepContext(h, H, r_max, H * r_max))
        w_h = theta + w
        if (pooled and w_next is not None and h >= 1 and not clipped
                and not rows.step_dependent and converged(w_h, w_next)
                and _fixed_policy(policy, rule, h)):
            w_next = w_h  # a fixed point: steps 0 .. h-1 would compute the same weights
            break
        w_next = w_h
    a0 = est.act(x0, 0)
    x0 = x0 if rows.x0 is None else rows.x0
    q0 = x0[np.arange(x0.shape[0]), a0] @ w_next
    return float(np.mean(np.clip(q0, 0.0, H * r_max)))


def _fixed_policy(policy: _Policy, rule, h: int) -> bool:
    """Whether steps ``0 .. h`` (their policies at ``1 .. h+1`` and the rule's per-factor
    parameters) are all step ``h``'s: the remaining pooled steps repeat the same map."""
    if not all(policy.same(j, h + 1) for j in range(1, h + 1)):
        return False
    if rule is None:
        return True
    ref = rule.factor_params(h)
    return all(np.array_equal(rule.factor_params(j), ref) if ref is not None
               else rule.factor_params(j) is None for j in range(h))
