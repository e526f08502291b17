"""Feature maps from observations x discrete actions onto the probability simplex.

Observation maps (scikit-learn transformers: ``fit`` learns ranges, ``transform`` maps):
:class:`NormalizedRBF`, :class:`TileCoding` (dense or ``scipy.sparse``),
:class:`StateAggregation`. :func:`cross_actions` places them block-wise by action, giving the
``feature_map(observations, actions) -> (n, d)`` that
:meth:`r2pvi.OfflineDataset.from_episodes` and ``estimator.as_policy`` take. Fitted maps save
to versioned ``.npz`` files (``fmap.save(path)``, :func:`load_feature_map`; no pickle).
"""

from ._io import load_feature_map, save_feature_map
from .maps import (
    ActionCrossing,
    NormalizedRBF,
    StateAggregation,
    TileCoding,
    as_feature_map,
    cross_actions,
)

__all__ = [
    "NormalizedRBF",
    "TileCoding",
    "StateAggregation",
    "ActionCrossing",
    "cross_actions",
    "as_feature_map",
    "save_feature_map",
    "load_feature_map",
]
