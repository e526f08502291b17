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
    Fitted-Q evaluation of the estimator's greedy policy ``pi``: backward over the steps,
    ridge regressions (the estimator's ``gamma`` unless ``gamma`` is given) of
    ``r_h + Q^pi_{h+1}(s_{h+1}, pi(s_{h+1}))`` on the held-out taken-action features give
    ``Q^pi_h = clip(phi^T w^pi_h, 0, (H - h) r_max)``; the score is the mean of
    ``Q^pi_0(s_0, pi(s_0))`` over the initial states (``initial_phi``: the features of every
    action there; by default ``dataset.initial_features()``). One regression over every
    held-out transition for a stationary dataset (as a pooled fit), one per step otherwise.
    The nominal value of ``pi``, in the units of the (shifted) rewards.
``"robust_fqe"``
    The same evaluation with the estimator's own step rule in place of the regression of
    the next values: the robust (regularized or constrained) value of ``pi`` under the
    estimator's uncertainty model, estimated from the held-out data.

See the user guide (``docs/user_guide/model-selection.md``) for what each one is good for
and how it fails.
"""

from __future__ import annotations

import numpy as np

from .._threads import limit_blas
from .._validation import as_float_array, check_choice, check_scalar
from ..data import OfflineDataset
from ._fqe import check_evaluation_dataset, policy_value

__all__ = ["SCORE_KINDS", "bellman_residual", "fqe_value", "Scorer", "score_estimator"]

SCORE_KINDS = ("bellman", "fqe", "robust_fqe")


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


def _initial_features(initial_phi, dataset, d: int, kind: str) -> np.ndarray:
    if initial_phi is None:
        initial_phi = dataset.initial_features()
        if initial_phi is None:
            raise ValueError(
                f"kind={kind!r} needs initial_phi: the features (n, A, d) of every action at "
                "the held-out initial states, or a callable dataset -> (n, A, d) (for cross-"
                "validation); this dataset stores only the taken action's features (datasets "
                "of episodes with a feature map crossed with the actions hold them: "
                "dataset.initial_features())")
    elif callable(initial_phi):
        initial_phi = initial_phi(dataset)
    arr = as_float_array(initial_phi, "initial_phi", ndim=3)
    if arr.shape[0] == 0 or arr.shape[2] != d:
        raise ValueError(f"initial_phi must have shape (n >= 1, A, d={d}), got {arr.shape}")
    return arr


def _pooled(pooled, dataset) -> bool:
    if isinstance(pooled, str):
        if pooled.lower() != "auto":
            raise ValueError(f"pooled must be 'auto', True or False, got {pooled!r}")
        return bool(dataset.stationary)
    if not isinstance(pooled, bool | np.bool_):
        raise TypeError(f"pooled must be 'auto', True or False, got {pooled!r}")
    return bool(pooled)


def fqe_value(est, dataset: OfflineDataset, initial_phi=None, *, robust: bool = False,
              pooled="auto", gamma=None, evaluation_map=None) -> float:
    """Fitted-Q evaluation of the estimator's greedy policy: the mean initial-state value.

    Parameters
    ----------
    est : fitted LinearEstimator
    dataset : OfflineDataset
        Held-out trajectories; the regressions use their transitions.
    initial_phi : array_like (n, A, d) or callable, optional
        Features of every action at the initial states to average over, or
        ``initial_phi(dataset) -> (n, A, d)`` (the held-out fold's own initial states).
        None: ``dataset.initial_features()`` (datasets of episodes hold them).
    robust : bool, default False
        False: the nominal value (each step a ridge regression of the next values).
        True: the robust value under the estimator's own uncertainty model (each step its
        step rule applied to the held-out ridge operator), see
        :mod:`r2pvi.algorithms._fqe`.
    pooled : "auto", True or False, default "auto"
        One regression over every held-out transition (True), or one per step (False);
        "auto": pooled for a :attr:`~r2pvi.OfflineDataset.stationary` dataset. It does not
        follow the estimator's own form, so that pooled and per-step fits are scored alike.
    gamma : float > 0, optional
        The evaluation's ridge parameter; None: the estimator's ``gamma``. Give one value to
        score estimators of different ``gamma`` alike. A large ``gamma`` against the
        features' mass (``sum phi_i^2`` over the held-out rows) pulls the values of rarely
        visited features to 0: see the user guide's model-selection page.
    evaluation_map : feature map, optional
        Nominal, pooled FQE only: regress on this map's features of the same observations
        (a map crossed with the actions, or a fitted observation transformer) instead of
        the dataset's own, while the policy acts on the dataset's; the initial states are
        the dataset's. One evaluation map scores estimators fitted with different maps on
        one scale. Needs a dataset of episodes stored as state features
        (:meth:`~r2pvi.OfflineDataset.from_episodes` with a crossed map).

    Returns
    -------
    float
        ``mean_i Q^pi_0(s_i, pi(s_i))``, in the units of the (shifted) rewards.
    """
    _check(est, dataset)
    kind = "robust_fqe" if robust else "fqe"
    pooled = _pooled(pooled, dataset)
    if evaluation_map is not None and (robust or not pooled or initial_phi is not None):
        raise ValueError(
            "evaluation_map is for kind='fqe' with pooled steps (a stationary dataset, or "
            "pooled=True) at the dataset's own initial states: drop initial_phi, use "
            "kind='fqe'")
    if evaluation_map is not None:
        check_evaluation_dataset(dataset)
    x0 = _initial_features(initial_phi, dataset, dataset.n_features, kind)
    if gamma is not None:
        gamma = check_scalar(gamma, "gamma", low=0.0, low_inclusive=False)
    with limit_blas():
        return policy_value(est, dataset, x0, robust=bool(robust), pooled=pooled,
                            gamma=gamma, evaluation_map=evaluation_map)


def score_estimator(est, dataset, kind: str = "bellman", *, initial_phi=None,
                    pooled="auto", gamma=None, evaluation_map=None) -> float:
    """The score of ``kind`` (higher is better); see :meth:`LinearEstimator.score`."""
    kind = check_choice(kind, "kind", SCORE_KINDS)
    if kind == "bellman":
        if initial_phi is not None:
            raise ValueError("initial_phi is used by kind='fqe' and 'robust_fqe' only; drop "
                             "it for 'bellman'")
        if (not (isinstance(pooled, str) and pooled == "auto") or gamma is not None
                or evaluation_map is not None):
            raise ValueError("pooled, gamma and evaluation_map are used by kind='fqe' and "
                             "'robust_fqe' only; drop them for 'bellman'")
        return -bellman_residual(est, dataset)
    return fqe_value(est, dataset, initial_phi, robust=kind == "robust_fqe", pooled=pooled,
                     gamma=gamma, evaluation_map=evaluation_map)


class Scorer:
    """A scoring callable ``scorer(est, dataset, y=None) -> float`` for scikit-learn.

    Pass it as ``scoring=`` to ``cross_val_score`` or ``GridSearchCV``; it returns
    ``est.score(dataset, kind, initial_phi=initial_phi, pooled=pooled)``.

    Parameters
    ----------
    kind : {"bellman", "fqe", "robust_fqe"}
    initial_phi : callable, optional
        For ``"fqe"`` and ``"robust_fqe"``: ``initial_phi(held_out_dataset) -> (n, A, d)``,
        the features of every action at the fold's initial states; None:
        ``held_out_dataset.initial_features()``.
    pooled : "auto", True or False, default "auto"
        The evaluation's form (see :func:`fqe_value`).
    gamma : float > 0, optional
        The evaluation's ridge parameter (None: each estimator's own).
    evaluation_map : feature map, optional
        ``"fqe"``: one map to evaluate every candidate with (see :func:`fqe_value`).

    Examples
    --------
    >>> from r2pvi.algorithms import Scorer
    >>> Scorer("bellman")
    Scorer('bellman')
    """

    def __init__(self, kind: str = "bellman", *, initial_phi=None, pooled="auto", gamma=None,
                 evaluation_map=None):
        self.kind = check_choice(kind, "kind", SCORE_KINDS)
        if evaluation_map is not None and self.kind != "fqe":
            raise ValueError("evaluation_map is used by kind='fqe' only")
        if initial_phi is not None and not callable(initial_phi):
            raise TypeError("initial_phi of a scorer must be a callable held-out dataset -> "
                            "(n, A, d): each fold has its own initial states")
        if self.kind == "bellman" and (initial_phi is not None or gamma is not None
                                       or not (isinstance(pooled, str) and pooled == "auto")):
            raise ValueError("initial_phi, pooled and gamma are used by kind='fqe' and "
                             "'robust_fqe' only; drop them for 'bellman'")
        if gamma is not None:
            gamma = check_scalar(gamma, "gamma", low=0.0, low_inclusive=False)
        self.initial_phi = initial_phi
        self.pooled = pooled
        self.gamma = gamma
        self.evaluation_map = evaluation_map

    def __call__(self, est, dataset, y=None) -> float:
        if self.kind == "bellman":
            return est.score(dataset, kind="bellman")
        return est.score(dataset, kind=self.kind, initial_phi=self.initial_phi,
                         pooled=self.pooled, gamma=self.gamma,
                         evaluation_map=self.evaluation_map)

    def __repr__(self) -> str:
        extra = "" if self.gamma is None else f", gamma={self.gamma!r}"
        if self.evaluation_map is not None:
            extra += f", evaluation_map={self.evaluation_map!r}"
        return f"Scorer({self.kind!r}{extra})"
