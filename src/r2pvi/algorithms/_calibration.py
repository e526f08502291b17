"""Calibration of a fitted-Q evaluation's setting on the behaviour policy's observed returns.

The held-out trajectories carry the returns of the policy that collected them. An
evaluation setting (the ridge parameter ``gamma`` and the feature map of the regressions)
that cannot reproduce them is mis-calibrated. For one setting, :func:`behaviour_weights`
runs fitted-Q evaluation of the **behaviour policy** on training trajectories, SARSA-style:
backward over the steps, pooled (one ridge regression over every transition of steps
``0 .. H-2``),

    Q^b_{H-1} = clip(phi^T theta, 0, r_max),
    Q^b_h(s, a) = clip(phi(s, a)^T (theta + E(v)), 0, (H - h) r_max),
    v = Q^b_{h+1}(s', a')   (a' the next *taken* action; known values where given),

with ``theta`` the ridge regression of the rewards and ``E`` the ridge operator of the
taken-action rows. :func:`calibration_errors` compares ``Q^b_0(s_0, a_0)`` at held-out
initial states with their observed returns, and reports the held-out one-step error of the
regression (the temporal-difference error of ``Q^b`` on held-out transitions).
Transitions whose next action is unknown (an episode truncated before the horizon) are
left out of the regressions.
"""

from __future__ import annotations

import numpy as np

from ..data import OfflineDataset
from ..data.episodes import absorbing_values
from ..data.storage.crossed import CrossedRows
from ..engine import pooled_steps
from ..engine.pooled import CrossedRidgeExpectation
from ._fqe import check_evaluation_dataset, evaluation_features

__all__ = ["behaviour_weights", "calibration_errors", "observed_returns"]


def _state_features(dataset: OfflineDataset, evaluation_map):
    """``(psi of the states (H, K, m), psi of the next states (H, K, m))``: the dataset's own
    or ``evaluation_map``'s."""
    if evaluation_map is None:
        psi = np.asarray(dataset._source.phi.psi)
        return psi[:-1], psi[1:]
    return evaluation_features(dataset, evaluation_map)


class _SarsaRows:
    """The pooled rows of a dataset of episodes for the behaviour's evaluation."""

    def __init__(self, dataset: OfflineDataset, evaluation_map=None):
        check_evaluation_dataset(dataset)
        H, K, A = dataset.horizon, dataset.n_trajectories, dataset.n_actions
        self.H, self.K, self.A = H, K, A
        actions = np.asarray(dataset._source.phi.actions)  # (H, K), -1 after the end
        psi, next_psi = _state_features(dataset, evaluation_map)
        P = pooled_steps(H)
        self.P = P
        self.terminal, self.terminal_value = absorbing_values(dataset)
        nxt_actions = np.full((H, K), -1, dtype=np.int64)
        nxt_actions[:-1] = actions[1:]
        taken = actions.copy()
        # a transition with no next action and no known value: left out (truncated early)
        drop = (np.arange(H)[:, None] < H - 1) & (nxt_actions < 0) & ~self.terminal
        taken[drop] = -1
        self.actions, self.next_actions = taken, nxt_actions
        self.psi, self.next_psi = psi, next_psi
        self.rewards = np.swapaxes(np.asarray(dataset.rewards, dtype=np.float64), 0, 1)
        self.offset = float(dataset._source.reward_offset)
        self.pooled_taken = CrossedRows(psi[:P].reshape(P * K, -1), taken[:P].reshape(-1), A)
        self.pooled_next = CrossedRows(next_psi[:P].reshape(P * K, -1),
                                       nxt_actions[:P].reshape(-1), A)
        # the known value at virtual step h of a row of step j: its own value, re-shifted
        steps = np.repeat(np.arange(P), K)
        self.known_rows = np.flatnonzero(self.terminal[:P].reshape(-1))
        self.known_base = (self.terminal_value[:P].reshape(-1)[self.known_rows]
                           - (H - steps[self.known_rows] - 1) * self.offset)

    def taken_values(self, psi: np.ndarray, actions: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``phi(s, a)^T w`` at the rows ``psi (n, m)`` and actions ``(n,)`` (0 for ``-1``)."""
        W = np.asarray(w, dtype=np.float64).reshape(self.A, -1)
        out = np.einsum("ij,ij->i", psi, W[np.maximum(actions, 0)])
        out[actions < 0] = 0.0
        return out


def behaviour_weights(dataset: OfflineDataset, gamma: float, evaluation_map=None,
                      r_max: float | None = None, rows: _SarsaRows | None = None) -> np.ndarray:
    """The weights ``(H, d)`` of the behaviour policy's ``Q^b_h`` by pooled SARSA-style
    fitted-Q evaluation on ``dataset`` (see the module docstring); ``d = A m`` with ``m``
    the state features of ``evaluation_map`` (None: the dataset's own)."""
    rows = _SarsaRows(dataset, evaluation_map) if rows is None else rows
    H = rows.H
    if r_max is None:
        r_max = _value_bound(dataset, rows)
    E = CrossedRidgeExpectation(rows.pooled_taken, gamma)
    theta = E(rows.rewards[:rows.P].reshape(-1))
    nxt = rows.pooled_next
    W = np.empty((H, theta.shape[0]))
    W[H - 1] = theta
    for h in range(H - 2, -1, -1):
        v = rows.taken_values(nxt.psi, nxt.actions, W[h + 1])
        np.clip(v, 0.0, (H - h - 1) * r_max, out=v)
        v[rows.known_rows] = rows.known_base + (H - h - 1) * rows.offset
        W[h] = theta + E(v)
    return W


def _value_bound(dataset: OfflineDataset, rows: _SarsaRows) -> float:
    """The largest value one step can add: the largest reward, or the offset of shifted
    rewards, which an absorbing state pays every step (above every reward when the original
    rewards are negative)."""
    return max(float(dataset.reward_range[1]), rows.offset, 0.0)


def observed_returns(dataset: OfflineDataset) -> np.ndarray:
    """Each trajectory's observed return ``(K,)`` in the dataset's (shifted) reward units:
    its rewards plus the known value of the absorbing state it ends in."""
    _, value = absorbing_values(dataset)
    return np.asarray(dataset.rewards, dtype=np.float64).sum(axis=1) + value.sum(axis=0)


def calibration_errors(train: OfflineDataset, held: OfflineDataset, gamma: float,
                       evaluation_map=None) -> dict:
    """Calibration of the setting ``(gamma, evaluation_map)``: behaviour FQE on ``train``,
    checked on ``held``.

    Returns
    -------
    dict
        ``bias``: mean predicted minus mean observed return at the held-out initial
        states; ``rmse``: the root mean squared error per trajectory; ``td``: the held-out
        mean squared one-step error ``(Q^b_h(s, a) - r - Q^b_{h+1}(s', a'))^2`` over every
        held-out transition.
    """
    W = behaviour_weights(train, gamma, evaluation_map)
    rows = _SarsaRows(held, evaluation_map)
    H = rows.H
    r_max = _value_bound(train, rows)
    q = np.empty((H, rows.K))
    for h in range(H):
        q[h] = np.clip(rows.taken_values(rows.psi[h], rows.actions[h], W[h]), 0.0,
                       (H - h) * r_max)
    G = observed_returns(held)
    pred = q[0]
    used = rows.actions[0] >= 0
    td_sum, n = 0.0, 0
    for h in range(H):
        sel = rows.actions[h] >= 0
        if h == H - 1:
            target = rows.rewards[h]
        else:
            nv = np.clip(rows.taken_values(rows.next_psi[h], rows.next_actions[h], W[h + 1]),
                         0.0, (H - h - 1) * r_max)
            nv = np.where(rows.terminal[h], rows.terminal_value[h], nv)
            target = rows.rewards[h] + nv
        td_sum += float(np.sum((q[h] - target)[sel] ** 2))
        n += int(sel.sum())
    return {"bias": float(pred[used].mean() - G[used].mean()),
            "rmse": float(np.sqrt(np.mean((pred[used] - G[used]) ** 2))),
            "td": td_sum / max(n, 1)}
