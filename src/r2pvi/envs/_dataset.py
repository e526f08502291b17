"""Turning simulated transitions into an :class:`~r2pvi.data.OfflineDataset`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..data import OfflineDataset

__all__ = ["Trajectories", "dataset_with_transitions"]


class Trajectories(NamedTuple):
    """K simulated trajectories of length H (0-based steps).

    ``states[k, h]`` is ``s_h``, ``actions[k, h]`` is ``a_h``, ``rewards[k, h]`` is ``r_h``
    and ``next_states[k, h]`` is ``s_{h+1}``. For the American put option the states are
    prices and a state after exercise is NaN.
    """

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray

    @property
    def returns(self) -> np.ndarray:
        """Undiscounted return of every trajectory, ``(K,)``."""
        return self.rewards.sum(axis=1)


def dataset_with_transitions(phi, rewards, next_phi, next_values, states, actions, next_states,
                             check_simplex: bool) -> OfflineDataset:
    """``OfflineDataset.from_features`` that also keeps the observed states and actions.

    The features are computed by the environment (they may depend on the step, which
    ``OfflineDataset.from_transitions`` cannot express); the states, actions and next states
    are attached exactly as ``from_transitions`` attaches them, so that ``ds.states``,
    ``ds.actions`` and ``ds.next_states`` work and survive ``save``/``load``/``subset``.
    """
    return OfflineDataset.from_features(
        phi, rewards, next_phi, next_values, check_simplex=check_simplex,
        states=states, actions=actions, next_states=next_states,
    )
