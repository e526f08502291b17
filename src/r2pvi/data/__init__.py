"""Offline datasets: the one :class:`OfflineDataset` over storage kinds.

- :mod:`r2pvi.data.dataset` — :class:`OfflineDataset` (properties, step access, subsets);
- :mod:`r2pvi.data.episodes` — episodes of any length (Gymnasium rollouts, Minari datasets);
- :mod:`r2pvi.data.neighbour_model` — :class:`NeighbourModel`, a nearest-neighbour model of
  a dataset of episodes that simulates a policy from the data alone (``score(kind="model")``);
- :mod:`r2pvi.data.storage` — where the numbers live (memory, dataset directories, Dask
  arrays, sparse rows, observations with a feature map), read one step at a time.
"""

from .dataset import OfflineDataset, SimplexFeatureWarning, check_simplex_features
from .neighbour_model import NeighbourModel

__all__ = ["OfflineDataset", "SimplexFeatureWarning", "check_simplex_features", "NeighbourModel"]
