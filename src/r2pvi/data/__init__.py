"""Offline datasets: the one :class:`OfflineDataset` over storage kinds.

- :mod:`r2pvi.data.dataset` — :class:`OfflineDataset` (properties, step access, subsets);
- :mod:`r2pvi.data.episodes` — episodes of any length (Gymnasium rollouts, Minari datasets);
- :mod:`r2pvi.data.storage` — where the numbers live (memory, dataset directories, Dask
  arrays, sparse rows, observations with a feature map), read one step at a time.
"""

from .dataset import OfflineDataset, SimplexFeatureWarning, check_simplex_features

__all__ = ["OfflineDataset", "SimplexFeatureWarning", "check_simplex_features"]
