"""Episodes of any length: the names of :mod:`r2pvi.data.episodes`, kept importable from here."""

from .data import episodes as _episodes
from .data.dataset import dataset_from_episodes
from .data.episodes import Episode, as_episode_list, episode_observations

__all__ = ["Episode", "dataset_from_episodes", "episode_observations", "as_episode_list"]
__doc__ = _episodes.__doc__  # the conventions (termination, truncation, padding, offsets)
