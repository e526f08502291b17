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
``"model"``
    The mean return of ``pi`` simulated in the nearest-neighbour model of the held-out
    episodes (:class:`~r2pvi.data.neighbour_model.NeighbourModel`) from their initial
    observations: each step takes the change of state of the nearest held-out transition of
    ``pi``'s action, and a rollout that leaves the data halts with value 0. ``pi`` follows
    its own state distribution instead of being regressed on the data's. In the units of
    the (shifted) rewards, as ``"fqe"``.

See the user guide (``docs/user_guide/model-selection.md``) for what each one is good for
and how it fails.
"""

from __future__ import annotations

import numpy as np

from .._threads import limit_blas
from .._validation import as_float_array, check_choice, check_scalar
from ..data import NeighbourModel, OfflineDataset
from ._fqe import check_evaluation_dataset, policy_value

__all__ = ["SCORE_KINDS", "bellman_residual", "fqe_value", "model_value", "Scorer",
           "score_estimator"]

SCORE_KINDS = ("bellman", "fqe", "robust_fqe", "model")
# the options of kind="model" and their defaults
MODEL_OPTIONS = {"n_neighbors": 1, "n_rollouts": 1, "random_state": 0}


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


def model_value(est, dataset: OfflineDataset, feature_map, *, n_neighbors: int = 1,
                n_rollouts: int = 1, random_state=0) -> float:
    """Mean simulated return of the estimator's greedy policy in the nearest-neighbour model
    of ``dataset``.

    Parameters
    ----------
    est : fitted LinearEstimator
    dataset : OfflineDataset
        Held-out episodes (:meth:`~r2pvi.OfflineDataset.from_episodes` with a map crossed
        with the actions): the model's transitions, and its initial observations.
    feature_map : callable or fitted transformer
        The map the dataset was built with; the policy acts through it on the model's
        observations (``est.as_policy(feature_map)``).
    n_neighbors : int >= 1, default 1
        Distinct nearest observations a transition is drawn from
        (:class:`~r2pvi.data.neighbour_model.NeighbourModel`).
    n_rollouts : int >= 1, default 1
        Rollouts from every initial observation.
    random_state : int, numpy.random.Generator or None, default 0
        The draws among neighbours (with ``n_neighbors=1`` and distinct observations the
        model is deterministic).

    Returns
    -------
    float
        The mean over the rollouts of the rewards over the horizon, plus the known value of
        the absorbing state a rollout ends in (0 from where it leaves the data and halts),
        in the units of the (shifted) rewards.
    """
    _check(est, dataset)
    if feature_map is None:
        raise ValueError("kind='model' needs feature_map: the map the dataset was built with "
                         "(the policy acts through it on the model's observations, as "
                         "est.as_policy(feature_map) does in an environment)")
    policy = est.as_policy(feature_map)
    model = NeighbourModel(dataset, n_neighbors)
    with limit_blas():
        returns = model.returns(policy, n_rollouts=n_rollouts, seed=random_state)
    return float(returns.mean())


def _no_options(kind: str, given: dict, owner: str) -> None:
    """Refuse the keywords ``given`` (used by ``owner`` only) for ``kind``."""
    used = list(given)
    if used:
        raise ValueError(f"{', '.join(used)} {'is' if len(used) == 1 else 'are'} used by "
                         f"{owner} only; drop {'it' if len(used) == 1 else 'them'} for "
                         f"kind={kind!r}")


def _model_options(kind: str, feature_map, n_neighbors, n_rollouts, random_state) -> dict:
    """The keywords of kind="model" given with values other than their defaults (refused
    for the other kinds)."""
    given = {} if feature_map is None else {"feature_map": feature_map}
    given.update({k: v for k, v in (("n_neighbors", n_neighbors), ("n_rollouts", n_rollouts),
                                    ("random_state", random_state))
                  if not (type(v) is int and v == MODEL_OPTIONS[k])})
    if kind != "model":
        _no_options(kind, given, "kind='model'")
    return given


def score_estimator(est, dataset, kind: str = "bellman", *, initial_phi=None,
                    pooled="auto", gamma=None, evaluation_map=None, feature_map=None,
                    n_neighbors=1, n_rollouts=1, random_state=0) -> float:
    """The score of ``kind`` (higher is better); see :meth:`LinearEstimator.score`."""
    kind = check_choice(kind, "kind", SCORE_KINDS)
    options = _model_options(kind, feature_map, n_neighbors, n_rollouts, random_state)
    auto = isinstance(pooled, str) and pooled == "auto"
    fqe_options = {"initial_phi": initial_phi, "pooled": None if auto else pooled,
                   "gamma": gamma, "evaluation_map": evaluation_map}
    fqe_given = {k: v for k, v in fqe_options.items() if v is not None}
    if kind in ("bellman", "model"):
        _no_options(kind, fqe_given, "kind='fqe' and 'robust_fqe'")
    if kind == "bellman":
        return -bellman_residual(est, dataset)
    if kind == "model":
        return model_value(est, dataset, **{"feature_map": None, **options})
    return fqe_value(est, dataset, initial_phi, robust=kind == "robust_fqe", pooled=pooled,
                     gamma=gamma, evaluation_map=evaluation_map)


class Scorer:
    """A scoring callable ``scorer(est, dataset, y=None) -> float`` for scikit-learn.

    Pass it as ``scoring=`` to ``cross_val_score`` or ``GridSearchCV``; it returns
    ``est.score(dataset, kind, ...)`` with the options given here.

    Parameters
    ----------
    kind : {"bellman", "fqe", "robust_fqe", "model"}
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
    feature_map, n_neighbors, n_rollouts, random_state
        ``"model"``: the map the datasets were built with (required) and the
        nearest-neighbour model's options (see :func:`model_value`).

    Examples
    --------
    >>> from r2pvi.algorithms import Scorer
    >>> Scorer("bellman")
    Scorer('bellman')
    >>> Scorer("model", feature_map=lambda obs, actions: obs, n_rollouts=3)
    Scorer('model', n_rollouts=3)
    """

    def __init__(self, kind: str = "bellman", *, initial_phi=None, pooled="auto", gamma=None,
                 evaluation_map=None, feature_map=None, n_neighbors=1, n_rollouts=1,
                 random_state=0):
        self.kind = check_choice(kind, "kind", SCORE_KINDS)
        if evaluation_map is not None and self.kind != "fqe":
            raise ValueError("evaluation_map is used by kind='fqe' only")
        if initial_phi is not None and not callable(initial_phi):
            raise TypeError("initial_phi of a scorer must be a callable held-out dataset -> "
                            "(n, A, d): each fold has its own initial states")
        if self.kind in ("bellman", "model") and (
                initial_phi is not None or gamma is not None
                or not (isinstance(pooled, str) and pooled == "auto")):
            raise ValueError("initial_phi, pooled and gamma are used by kind='fqe' and "
                             f"'robust_fqe' only; drop them for {self.kind!r}")
        self._model = _model_options(self.kind, feature_map, n_neighbors, n_rollouts,
                                     random_state)
        if self.kind == "model" and feature_map is None:
            raise ValueError("Scorer('model') needs feature_map: the map the datasets were "
                             "built with")
        self.feature_map = feature_map
        if gamma is not None:
            gamma = check_scalar(gamma, "gamma", low=0.0, low_inclusive=False)
        self.initial_phi = initial_phi
        self.pooled = pooled
        self.gamma = gamma
        self.evaluation_map = evaluation_map

    def __call__(self, est, dataset, y=None) -> float:
        if self.kind == "bellman":
            return est.score(dataset, kind="bellman")
        if self.kind == "model":
            return est.score(dataset, kind="model", **self._model)
        return est.score(dataset, kind=self.kind, initial_phi=self.initial_phi,
                         pooled=self.pooled, gamma=self.gamma,
                         evaluation_map=self.evaluation_map)

    def __repr__(self) -> str:
        extra = "" if self.gamma is None else f", gamma={self.gamma!r}"
        if self.evaluation_map is not None:
            extra += f", evaluation_map={self.evaluation_map!r}"
        extra += "".join(f", {k}={v!r}" for k, v in self._model.items() if k != "feature_map")
        return f"Scorer({self.kind!r}{extra})"
