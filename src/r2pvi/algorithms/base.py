"""What every estimator shares: parameters, validation, fitting through the engine, acting, I/O.

The conventions are scikit-learn's: ``__init__`` only stores keyword parameters, ``fit``
validates them and returns ``self``, fitted attributes end with ``_``, and
``get_params``/``set_params`` expose the parameters.
"""

from __future__ import annotations

import inspect
import numbers

import numpy as np

from .._compat import KeywordParams, SklearnCompatMixin, not_fitted_error
from .._io import save_npz
from .._threads import limit_blas
from .._validation import as_float_array, check_choice, check_scalar, plain
from ..data import OfflineDataset
from ..duals.gram import GramFactor, GramMatrixError
from ..engine import PENALTIES, FittedModel, StepRule, backward_induction, q_values_from_model
from ..engine.diagnostics import warn_if_starved
from ..engine.sizing import warn_if_oversized
from ._model_file import (
    ESTIMATOR_REGISTRY,
    MODEL_FORMAT_VERSION,
    _jsonable,
    _pack_elliptical,
    load_model,
)
from ._reward_range import check_reward_range

__all__ = ["LinearEstimator", "load_estimator", "ESTIMATOR_REGISTRY"]

_FITTED = ("weights_", "reward_weights_", "gram_inv_diag_")


def _check_r_max(r_max, dataset) -> float:
    """``r_max > 0``; a zero taken from data whose rewards are all 0 is named as such."""
    value = check_scalar(r_max, "r_max")
    offset = float(getattr(getattr(dataset, "_source", None), "reward_offset", 0.0) or 0.0)
    if 0 < value < offset and getattr(dataset, "has_known_values", False):
        raise ValueError(
            f"r_max={value!r} is below this dataset's reward offset c={offset!r}: its "
            f"episodes end in absorbing states, which pay c at every remaining step, so the "
            f"values of the other states would be clipped below theirs (Q_h <= (H - h) "
            f"r_max). Pass r_max >= {offset!r} (the bound of the shifted rewards and of c)")
    if value > 0:
        return value
    low, high = dataset.reward_range if value == 0 else (None, None)
    if high == 0 and low == 0:
        raise ValueError(
            "r_max must be > 0, got 0.0: every reward in the data is 0 (data.reward_range = "
            "(0.0, 0.0); e.g. -1 per step shifted by reward_offset), so r_max cannot come from "
            "the data's rewards. Pass the task's bound of the shifted rewards, at least the "
            "offset c (the absorbing goal state pays c per remaining step): r_max=1.0 for "
            "-1 per step shifted by reward_offset='auto'. If no episode reached the goal, the "
            "data cannot tell policies apart: collect episodes that reach it")
    raise ValueError(f"r_max must be > 0, got {value!r}")


class LinearEstimator(KeywordParams, SklearnCompatMixin):
    """Base class of the pessimistic value-iteration estimators (PEVI, R2PVI, DRPVI, ...).

    Subclasses declare their parameters in ``__init__`` and implement :meth:`_make_rule`
    (the engine's :class:`~r2pvi.engine.StepRule`) and, when they have parameters of their
    own, :meth:`_validate_extra`.
    """

    _penalty_choices = PENALTIES
    # Factorization of the Gram matrices ("auto": primal or dual from the shapes); tests and
    # benchmarks force "primal"/"dual" to compare the two exact forms.
    _gram_form = "auto"
    # Parameters every subclass stores in __init__ (declared for type checkers).
    beta: float
    gamma: float
    r_max: float
    reward_weights: np.ndarray | None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        ESTIMATOR_REGISTRY[cls.__name__] = cls

    # ------------------------------------------------------------------ parameters
    def __repr__(self) -> str:
        defaults = {
            p.name: p.default
            for p in inspect.signature(type(self).__init__).parameters.values()
            if p.name != "self"
        }
        shown = []
        for name, value in self.get_params().items():
            default = defaults.get(name, inspect.Parameter.empty)
            same = value is default or (
                not isinstance(value, np.ndarray)
                and not isinstance(default, np.ndarray)
                and type(value) is type(default)
                and value == default
            )
            if not same:
                shown.append(f"{name}={value!r}")
        return f"{type(self).__name__}({', '.join(shown)})"

    # ------------------------------------------------------------------ validation
    def _validate_common(self, dataset: OfflineDataset) -> dict:
        if isinstance(self.beta, str):
            raise ValueError(
                f"{type(self).__name__} takes a number for beta, got {self.beta!r}; "
                "beta='theory' (the paper's theorem) exists for R2PVI with 'tv', 'kl' or 'chi2'"
            )
        p: dict = {
            "beta": check_scalar(self.beta, "beta", low=0.0),
            "gamma": check_scalar(self.gamma, "gamma", low=0.0, low_inclusive=False),
            "r_max": _check_r_max(self.r_max, dataset),
            "penalty": check_choice(
                getattr(self, "penalty", "elliptical"), "penalty", self._penalty_choices
            ),
        }
        if self.reward_weights is None:
            p["reward_weights"] = None
        else:
            rw = as_float_array(self.reward_weights, "reward_weights", ndim=2)
            expected = (dataset.horizon, dataset.n_features)
            if rw.shape != expected:
                raise ValueError(
                    f"reward_weights must have shape (H, d) = {expected} to match the dataset, "
                    f"got {rw.shape}; pass None to estimate them from the rewards"
                )
            p["reward_weights"] = rw
        return p

    def _validate_extra(self, dataset: OfflineDataset) -> dict:
        return {}

    def _make_rule(self, params: dict) -> StepRule:
        raise NotImplementedError

    # ------------------------------------------------------------------ fitting
    def _time_homogeneous(self, dataset=None) -> bool:
        """Whether to pool the steps (one Gram matrix for all): ``time_homogeneous``, with
        "auto" resolved by ``dataset.stationary`` (per step without a dataset)."""
        value = getattr(self, "time_homogeneous", False)
        if isinstance(value, str) and value.lower() == "auto":
            return bool(getattr(dataset, "stationary", False))
        if not isinstance(value, bool | np.bool_):
            raise TypeError(f"time_homogeneous must be 'auto', True or False, got "
                            f"{plain(value)!r}")
        return bool(value)

    def _run_engine(self, dataset: OfflineDataset, params: dict, sample_weights=None,
                    value_moments: bool = False):
        try:
            return backward_induction(
                dataset,
                self._make_rule(params),
                beta=params["beta"],
                gamma=params["gamma"],
                penalty=params["penalty"],
                r_max=params["r_max"],
                reward_weights=params["reward_weights"],
                sample_weights=sample_weights,
                time_homogeneous=params.get("time_homogeneous", False),
                form=self._gram_form,
                value_moments=value_moments,
            )
        except GramMatrixError as exc:
            raise _gram_error_with_step(exc, dataset, params["gamma"], sample_weights) from None

    def _fit_model(self, dataset: OfflineDataset, params: dict) -> FittedModel:
        """The fitted model; variance-aware subclasses override this with two passes."""
        return self._run_engine(dataset, params)

    def fit(self, dataset: OfflineDataset, y=None):
        """Learn the weights of every step from ``dataset``; returns ``self``.

        ``y`` is ignored (scikit-learn's signature: the rewards are in the dataset).

        Raises ``ValueError`` when the rewards (or those of ``reward_weights``) leave
        ``[0, r_max]``, naming the ``r_max`` to pass or the shift to apply (see
        :func:`check_reward_range`): the clip of ``Q_h`` to ``[0, (H - h) r_max]`` would
        otherwise change the values silently.

        Sets ``fit_report_`` (:class:`~r2pvi.engine.diagnostics.FitDiagnostics`: rows,
        shrinkage of a constant target, absorbing transitions of each regression) and warns
        (:class:`~r2pvi.StarvedFitWarning`) when a per-step fit starves, and
        (:class:`~r2pvi.FeatureSizeWarning`) when the features ``d`` outnumber the
        transitions of every regression (per step, or pooled)."""
        if not isinstance(dataset, OfflineDataset):
            raise TypeError(
                f"fit expects an r2pvi.OfflineDataset, got {type(dataset).__name__}; build one "
                "with OfflineDataset.from_features(...)"
            )
        params = self._validate_common(dataset)
        params.update(self._validate_extra(dataset))
        params["time_homogeneous"] = self._time_homogeneous(dataset)
        check_reward_range(dataset, params["r_max"], params["reward_weights"])
        with limit_blas():  # one BLAS thread by default: see r2pvi._threads
            model = self._fit_model(dataset, params)
        self._set_fitted(model, params, dataset.n_actions)
        # What the fit saw of its regressions; a per-step fit that cannot learn says so.
        self.fit_report_ = model.diagnostics
        warn_if_starved(self.fit_report_)
        warn_if_oversized(self.fit_report_, dataset.n_features, dataset.n_trajectories)
        return self

    def _set_fitted(self, model: FittedModel, params: dict, n_actions: int):
        self.weights_ = model.weights
        self.reward_weights_ = model.reward_weights
        self.gram_inv_diag_ = model.gram_inv_diag
        self._elliptical = model.elliptical  # acting's cached factors (elliptical penalty)
        self.horizon_, self.n_features_in_ = model.weights.shape
        self.n_actions_ = n_actions
        self._fit_params = {k: params[k] for k in ("beta", "penalty", "r_max")}

    def _check_fitted(self):
        if not hasattr(self, "weights_"):
            raise not_fitted_error()(
                f"this {type(self).__name__} is not fitted yet; call fit(dataset) first"
            )

    def _model(self) -> FittedModel:
        return FittedModel(
            self.weights_, self.reward_weights_, self.gram_inv_diag_,
            getattr(self, "_elliptical", None),
        )

    # ------------------------------------------------------------------ acting
    def q_values(self, phi_all, h: int, known_values=None) -> np.ndarray:
        """``Q_h`` of every action: features ``phi_all (n, A, d)`` -> ``(n, A)``.

        ``h`` is the 0-based step. ``known_values (n, A)`` overrides actions whose value is
        known (NaN: use the learned Q), as in the dataset.
        """
        self._check_fitted()
        phi_all = as_float_array(phi_all, "phi_all", copy=False)  # read only
        if phi_all.ndim == 2:
            raise ValueError(
                "phi_all must have shape (n, A, d); for one state pass phi_all[None]"
            )
        if phi_all.ndim != 3 or phi_all.shape[-1] != self.n_features_in_:
            raise ValueError(
                f"phi_all must have shape (n, A, d={self.n_features_in_}), got {phi_all.shape}"
            )
        if isinstance(h, bool) or not isinstance(h, numbers.Integral):
            raise TypeError(f"h must be an integer step in [0, {self.horizon_}), got {h!r}")
        if not 0 <= h < self.horizon_:
            raise ValueError(f"h must be a 0-based step in [0, {self.horizon_}), got {h}")
        if known_values is not None:
            known_values = as_float_array(known_values, "known_values", allow_nan=True)
            if known_values.shape != phi_all.shape[:2]:
                raise ValueError(
                    f"known_values must have shape (n, A) = {phi_all.shape[:2]}, "
                    f"got {known_values.shape}"
                )
        fp = self._fit_params
        return q_values_from_model(
            self._model(), phi_all, int(h), penalty=fp["penalty"], beta=fp["beta"],
            r_max=fp["r_max"], known_values=known_values,
        )

    def act(self, phi_all, h: int, known_values=None) -> np.ndarray:
        """Greedy action indices ``(n,)`` at step ``h`` (ties go to the lowest index)."""
        return np.argmax(self.q_values(phi_all, h, known_values), axis=1)

    def values(self, phi_all, h: int, known_values=None) -> np.ndarray:
        """Greedy values ``V_h = max_a Q_h`` at step ``h``, ``(n,)``."""
        return np.max(self.q_values(phi_all, h, known_values), axis=1)

    def as_policy(self, feature_map, *, beyond_horizon: str = "receding"):
        """This fitted estimator as a policy ``(h, observations) -> actions`` for Gymnasium.

        ``feature_map`` is the one the dataset was built with (see
        :class:`~r2pvi.algorithms._policy.GreedyPolicy`); the policy works with
        :func:`r2pvi.envs.collect_episodes` and :func:`r2pvi.evaluation.evaluate_policy`.
        """
        from ._policy import GreedyPolicy

        self._check_fitted()
        return GreedyPolicy(self, feature_map, beyond_horizon=beyond_horizon)

    # ------------------------------------------------------------------ scoring
    def score(self, dataset: OfflineDataset, y=None, *, kind: str = "bellman",
              initial_phi=None, pooled="auto", gamma=None, evaluation_map=None,
              feature_map=None, n_neighbors: int = 1, n_rollouts: int = 1,
              random_state=0) -> float:
        """A score of the fitted estimator on held-out trajectories; higher is better.

        Parameters
        ----------
        dataset : OfflineDataset
            Held-out trajectories (``dataset[test_indices]``), with the fitted H and d.
        y : None
            Ignored (scikit-learn's signature).
        kind : {"bellman", "fqe", "robust_fqe", "model"}, default "bellman"
            ``"bellman"``: minus the mean squared nominal Bellman residual
            ``(Q_h(s, a) - r - V_{h+1}(s'))^2`` of the fitted ``Q`` over the held-out
            transitions (0 is a perfect fit). ``"fqe"``: fitted-Q evaluation of the greedy
            policy's mean initial-state value on the held-out data (rewards' units).
            ``"robust_fqe"``: the same with the estimator's own step rule in place of the
            regression of the next values, i.e. the policy's robust value under the
            estimator's uncertainty model (see :mod:`r2pvi.algorithms._fqe`).
            ``"model"``: the greedy policy's mean return simulated in the nearest-neighbour
            model of the held-out episodes (see
            :class:`~r2pvi.data.neighbour_model.NeighbourModel`; rewards' units).
        initial_phi : array_like (n, A, d) or callable, optional
            ``"fqe"``/``"robust_fqe"`` only: features of every action at the initial
            states, or ``initial_phi(dataset) -> (n, A, d)``; None takes
            ``dataset.initial_features()`` (datasets of episodes hold them).
        pooled : "auto", True or False, default "auto"
            ``"fqe"``/``"robust_fqe"``: one regression over every held-out transition, or
            one per step; "auto" pools a stationary dataset's steps (whatever the form
            the estimator was fitted with, so that both forms are scored alike).
        gamma : float > 0, optional
            ``"fqe"``/``"robust_fqe"``: the evaluation's ridge parameter; None: this
            estimator's ``gamma``.
        evaluation_map : feature map, optional
            ``"fqe"`` with pooled steps: regress on this map's features of the held-out
            observations (the policy still acts on this estimator's): one scale for
            estimators fitted with different maps.
        feature_map : callable or fitted transformer
            ``"model"`` only, required: the map the dataset was built with.
        n_neighbors, n_rollouts, random_state : int, int, int or Generator
            ``"model"`` only: distinct nearest observations a transition is drawn from
            (default 1), rollouts from every held-out initial observation (default 1), the
            draws' seed (default 0). See :func:`r2pvi.algorithms._score.model_value`.

        Returns
        -------
        float

        See Also
        --------
        r2pvi.algorithms.Scorer : the same as a ``scoring=`` callable for scikit-learn.

        Examples
        --------
        >>> import numpy as np
        >>> from r2pvi import PEVI, OfflineDataset
        >>> rng = np.random.default_rng(0)
        >>> ds = OfflineDataset.from_features(rng.dirichlet(np.ones(3), (40, 2)),
        ...                                   rng.random((40, 2)),
        ...                                   rng.dirichlet(np.ones(3), (40, 2, 2)))
        >>> est = PEVI(beta=0.0).fit(ds[:30])
        >>> bool(est.score(ds[30:]) <= 0.0)
        True
        """
        from ._score import score_estimator

        return score_estimator(self, dataset, kind, initial_phi=initial_phi, pooled=pooled,
                               gamma=gamma, evaluation_map=evaluation_map,
                               feature_map=feature_map, n_neighbors=n_neighbors,
                               n_rollouts=n_rollouts, random_state=random_state)

    # ------------------------------------------------------------------ I/O
    def _params_to_json(self) -> tuple[dict, dict]:
        meta, arrays = {}, {}
        for name, value in self.get_params().items():
            if isinstance(value, np.ndarray) or (
                isinstance(value, list | tuple) and np.ndim(value) > 0
            ):
                arrays["param_" + name] = np.asarray(value, dtype=float)
                meta[name] = {"__array__": "param_" + name}
            else:
                meta[name] = _jsonable(name, value)
        return meta, arrays

    def save(self, path):
        """Save the fitted estimator to a versioned ``.npz`` (arrays + JSON header, no pickle).

        Returns the path written. Load it back with :meth:`load` or :func:`r2pvi.load`.
        """
        self._check_fitted()
        params, arrays = self._params_to_json()
        for name in _FITTED:
            arrays[name] = getattr(self, name)
        meta = {
            "estimator": type(self).__name__,
            "params": params,
            "fit_params": self._fit_params,
            "n_actions": self.n_actions_,
        }
        if getattr(self, "_elliptical", None) is not None:
            index, packed, kinds = _pack_elliptical(self._elliptical)
            arrays.update(packed)
            meta["elliptical_index"] = index
            meta["elliptical_kinds"] = kinds
        return save_npz(path, "estimator", MODEL_FORMAT_VERSION, arrays, meta)

    @classmethod
    def load(cls, path):
        """Load an estimator saved by :meth:`save`; it is fitted and ready to act."""
        est = load_estimator(path)
        if cls is not LinearEstimator and not isinstance(est, cls):
            raise TypeError(f"{path} holds a {type(est).__name__}, not a {cls.__name__}")
        return est


def _gram_error_with_step(exc, dataset, gamma, sample_weights) -> GramMatrixError:
    """The same error, naming the (0-based) step whose Gram matrix has no Cholesky factor."""
    for h in range(dataset.horizon - 1, -1, -1):
        sw = None if sample_weights is None else sample_weights[h]
        try:
            GramFactor(dataset.step(h)[0], gamma, sw)
        except GramMatrixError:
            return GramMatrixError(f"step h = {h} (0-based): {exc}")
    return exc


def load_estimator(path):
    """Load any estimator saved with ``save`` (dispatches on the class recorded in the file).

    Every field is checked, ranges included: the parameters go through the same checks as
    ``fit``, and the fitted arrays must have consistent shapes, finite entries and the
    values a fit can produce (see :mod:`r2pvi.algorithms._model_file`). A bad file raises a
    ``ValueError`` naming the file and the field.
    """
    return load_model(path)
