"""A fitted estimator and a feature map as a policy for Gymnasium environments."""

from __future__ import annotations

import numpy as np

from .._validation import check_choice
from ..features.maps import as_feature_map

__all__ = ["GreedyPolicy", "BEYOND_HORIZON"]

BEYOND_HORIZON = ("receding", "last", "error")


class GreedyPolicy:
    """``policy(h, observations) -> actions``: greedy in the estimator's ``Q_h``.

    Built by ``estimator.as_policy(feature_map)``. Batched: ``h`` is an integer or an
    ``(n,)`` array of steps (the sub-environments of a vector environment are at different
    steps) and ``observations`` an ``(n, ...)`` batch. Ties go to the lowest action.

    Parameters
    ----------
    estimator : fitted LinearEstimator
    feature_map : callable or fitted transformer
        The map the dataset was built with: ``feature_map(observations, actions) -> (n, d)``,
        or an observation transformer crossed with the actions.
    beyond_horizon : {"receding", "last", "error"}, default "receding"
        Steps ``h >= H`` (an environment whose episodes outlast the data's horizon):
        ``"receding"`` acts with ``Q_0`` (as if H steps remained: receding-horizon control,
        sensible when the dynamics do not depend on h), ``"last"`` with ``Q_{H-1}``,
        ``"error"`` raises.

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import OfflineDataset, PEVI
    >>> from r2pvi.features import StateAggregation, cross_actions
    >>> fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), n_actions=2)
    >>> ep = {"observations": [[0.1], [0.9], [0.9]], "actions": [1, 1], "rewards": [0.0, 1.0],
    ...       "terminations": [False, False], "truncations": [False, True]}
    >>> est = PEVI(beta=0.0, time_homogeneous=False).fit(
    ...     OfflineDataset.from_episodes([ep], fmap, 2))
    >>> policy = est.as_policy(fmap)
    >>> policy(np.array([0, 1, 7]), np.array([[0.1], [0.9], [0.1]]))   # h = 7 >= H: Q_0
    array([1, 1, 1])
    """

    def __init__(self, estimator, feature_map, *, beyond_horizon: str = "receding"):
        if not hasattr(estimator, "weights_"):
            raise RuntimeError(
                f"the {type(estimator).__name__} is not fitted yet; call fit(dataset) before "
                "as_policy(feature_map)"
            )
        beyond_horizon = check_choice(beyond_horizon, "beyond_horizon", BEYOND_HORIZON)
        self.estimator = estimator
        self.n_actions = int(estimator.n_actions_)
        self.feature_map = as_feature_map(feature_map, self.n_actions)
        self.beyond_horizon = beyond_horizon
        self.horizon = int(estimator.horizon_)

    def features(self, observations) -> np.ndarray:
        """``phi(o, a)`` of every action at every observation, ``(n, A, d)``."""
        fm = self.feature_map
        if callable(getattr(fm, "all_actions", None)):
            phi = fm.all_actions(observations)
        else:
            obs = np.asarray(observations)
            n = obs.shape[0]
            cols = [fm(obs, np.full(n, a, dtype=np.int64)) for a in range(self.n_actions)]
            phi = np.stack([c.toarray() if hasattr(c, "toarray") else np.asarray(c, float)
                            for c in cols], axis=1)
        d = self.estimator.n_features_in_
        if phi.ndim != 3 or phi.shape[2] != d:
            raise ValueError(
                f"feature_map gives {phi.shape[-1]} features but the estimator was fitted on "
                f"d = {d}: pass the feature map the dataset was built with"
            )
        return phi

    def steps(self, h, n: int) -> np.ndarray:
        """The estimator's step used at each row: ``h`` mapped into ``[0, H)``."""
        h = np.broadcast_to(np.asarray(h, dtype=np.int64), (n,))
        if (h < 0).any():
            raise ValueError(f"steps h must be >= 0, got {h.min()}")
        late = h >= self.horizon
        if late.any():
            if self.beyond_horizon == "error":
                raise ValueError(
                    f"step {int(h.max())} is beyond the fitted horizon H = {self.horizon}; "
                    "use beyond_horizon='receding' or 'last', or cut episodes at H "
                    "(max_steps=H)"
                )
            h = np.where(late, 0 if self.beyond_horizon == "receding" else self.horizon - 1, h)
        return h

    def q_values(self, h, observations) -> np.ndarray:
        """``Q_h(o, a)`` of every action, ``(n, A)``."""
        phi = self.features(observations)
        n = phi.shape[0]
        steps = self.steps(h, n)
        q = np.empty((n, self.n_actions))
        for step in np.unique(steps):
            rows = steps == step
            q[rows] = self.estimator.q_values(phi[rows], int(step))
        return q

    def __call__(self, h, observations) -> np.ndarray:
        """Greedy actions ``(n,)`` (ties to the lowest index)."""
        return np.argmax(self.q_values(h, observations), axis=1)

    def __repr__(self) -> str:
        return f"GreedyPolicy({type(self.estimator).__name__}, H={self.horizon})"
