"""Scores of a fitted estimator on held-out trajectories (higher is better).

Two scores, both computed from the held-out data alone (no simulator):

``"bellman"``
    The negative mean squared Bellman residual of the fitted ``Q`` under the nominal model:
    for every held-out transition ``(s_h, a_h, r_h, s_{h+1})``,
    ``(Q_h(s_h, a_h) - r_h - V_{h+1}(s_{h+1}))^2`` with ``V_{h+1} = max_a Q_{h+1}``
    (known next-state values where the dataset gives them, ``V_H = 0``), ``Q`` exactly as the
    estimator acts with it (penalty and clip included), averaged over the ``K H``
    transitions and negated.
``"fqe"``
    Fitted-Q evaluation of the estimator's greedy policy ``pi``: backward over the steps, a
    ridge regression (the estimator's ``gamma``) of ``r_h + Q^pi_{h+1}(s_{h+1},
    pi(s_{h+1}))`` on the held-out taken-action features gives ``Q^pi_h = clip(phi^T w^pi_h,
    0, (H - h) r_max)``; the score is the mean of ``Q^pi_0(s_0, pi(s_0))`` over the initial
    states given by ``initial_phi`` (the features of every action there, which an
    :class:`~r2pvi.OfflineDataset` does not hold: it stores only the taken action's).

See the user guide (``docs/user_guide/model-selection.md``) for what each one is good for
and how it fails.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_float_array, check_choice
from ..data import OfflineDataset
from ..duals import GramFactor

__all__ = ["SCORE_KINDS", "bellman_residual", "fqe_value", "Scorer", "score_estimator"]

SCORE_KINDS = ("bellman", "fqe")


def _dense(x) -> np.ndarray:
    """Step features as a float64 array (sparse rows are densified, one step at a time)."""
    if hasattr(x, "lead") and hasattr(x, "matrix"):  # StackedSparse (..., d)
        return x.matrix.toarray().reshape(*x.lead, x.matrix.shape[1])
    if hasattr(x, "toarray"):  # CSR (K, d)
        return x.toarray()
    return np.asarray(x, dtype=np.float64)


def _check(est, dataset) -> None:
    est._check_fitted()
    if not isinstance(dataset, OfflineDataset):
        raise TypeError(f"score expects an r2pvi.OfflineDataset of held-out trajectories, got "
                        f"{type(dataset).__name__}")
    shape = (dataset.horizon, dataset.n_features)
    if shape != (est.horizon_, est.n_features_in_):
        raise ValueError(
            f"dataset must have the fitted (H, d) = {(est.horizon_, est.n_features_in_)}, "
            f"got {shape}")


def _next_values(est, nphi, known, h: int, H: int) -> np.ndarray:
    """``V_{h+1}`` of the estimator at step ``h``'s next states (0 after the last step)."""
    if h == H - 1:
        return np.zeros(nphi.shape[0])
    return est.values(nphi, h + 1, known)


def bellman_residual(est, dataset: OfflineDataset) -> float:
    """Mean squared nominal Bellman residual of the fitted ``Q`` on ``dataset`` (>= 0).

    ``mean_{k, h} (Q_h(s_h^k, a_h^k) - r_h^k - V_{h+1}(s_{h+1}^k))^2``, with ``Q`` and
    ``V = max_a Q`` exactly as the estimator acts (penalty, clip, known values).
    """
    _check(est, dataset)
    H, K = dataset.horizon, dataset.n_trajectories
    total = 0.0
    for h in range(H):
        phi, r, nphi, known = dataset.step(h)
        phi, nphi = _dense(phi), _dense(nphi)
        q = est.q_values(phi[:, None, :], h)[:, 0]
        v = _next_values(est, nphi, known, h, H)
        total += float(np.sum((q - np.asarray(r, dtype=np.float64) - v) ** 2))
    return total / (K * H)


def _initial_features(initial_phi, dataset, d: int) -> np.ndarray:
    if initial_phi is None:
        raise ValueError(
            "kind='fqe' needs initial_phi: the features (n, A, d) of every action at the "
            "held-out initial states, or a callable dataset -> (n, A, d) (for cross-"
            "validation); a dataset stores only the taken action's features")
    if callable(initial_phi):
        initial_phi = initial_phi(dataset)
    arr = as_float_array(initial_phi, "initial_phi", ndim=3)
    if arr.shape[0] == 0 or arr.shape[2] != d:
        raise ValueError(f"initial_phi must have shape (n >= 1, A, d={d}), got {arr.shape}")
    return arr


def fqe_value(est, dataset: OfflineDataset, initial_phi) -> float:
    """Fitted-Q evaluation of the estimator's greedy policy: the mean initial-state value.

    Parameters
    ----------
    est : fitted LinearEstimator
    dataset : OfflineDataset
        Held-out trajectories; the regression of each step uses its transitions.
    initial_phi : array_like (n, A, d) or callable
        Features of every action at the initial states to average over, or
        ``initial_phi(dataset) -> (n, A, d)`` (the held-out fold's own initial states).

    Returns
    -------
    float
        ``mean_i Q^pi_0(s_i, pi(s_i))``, in the units of the rewards.
    """
    _check(est, dataset)
    x0 = _initial_features(initial_phi, dataset, dataset.n_features)
    H = dataset.horizon
    r_max = est._fit_params["r_max"]
    w_next = None
    for h in range(H - 1, -1, -1):
        phi, r, nphi, known = dataset.step(h)
        nphi = _dense(nphi)
        y = np.array(r, dtype=np.float64)
        if h < H - 1:
            act = est.act(nphi, h + 1, known)
            rows = np.arange(nphi.shape[0])
            q_pi = np.clip(nphi[rows, act] @ w_next, 0.0, (H - h - 1) * r_max)
            if known is not None:
                k = np.asarray(known, dtype=np.float64)[rows, act]
                q_pi = np.where(np.isnan(k), q_pi, k)
            y += q_pi
        w_next = GramFactor(phi, float(est.gamma)).regress(y)  # the fit's ridge regression
    a0 = est.act(x0, 0)
    return float(np.mean(np.clip(x0[np.arange(x0.shape[0]), a0] @ w_next, 0.0, H * r_max)))


def score_estimator(est, dataset, kind: str = "bellman", *, initial_phi=None) -> float:
    """The score of ``kind`` (higher is better); see :meth:`LinearEstimator.score`."""
    kind = check_choice(kind, "kind", SCORE_KINDS)
    if kind == "bellman":
        if initial_phi is not None:
            raise ValueError("initial_phi is used by kind='fqe' only; drop it for 'bellman'")
        return -bellman_residual(est, dataset)
    return fqe_value(est, dataset, initial_phi)


class Scorer:
    """A scoring callable ``scorer(est, dataset, y=None) -> float`` for scikit-learn.

    Pass it as ``scoring=`` to ``cross_val_score`` or ``GridSearchCV``; it returns
    ``est.score(dataset, kind, initial_phi=initial_phi)``.

    Parameters
    ----------
    kind : {"bellman", "fqe"}
    initial_phi : callable, optional
        For ``"fqe"``: ``initial_phi(held_out_dataset) -> (n, A, d)``, the features of
        every action at the fold's initial states.

    Examples
    --------
    >>> from r2pvi.algorithms import Scorer
    >>> Scorer("bellman")
    Scorer('bellman')
    """

    def __init__(self, kind: str = "bellman", *, initial_phi=None):
        self.kind = check_choice(kind, "kind", SCORE_KINDS)
        if initial_phi is not None and not callable(initial_phi):
            raise TypeError("initial_phi of a scorer must be a callable held-out dataset -> "
                            "(n, A, d): each fold has its own initial states")
        self.initial_phi = initial_phi

    def __call__(self, est, dataset, y=None) -> float:
        return est.score(dataset, kind=self.kind, initial_phi=self.initial_phi)

    def __repr__(self) -> str:
        return f"Scorer({self.kind!r})"
