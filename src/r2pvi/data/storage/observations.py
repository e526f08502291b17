"""Observations and a feature map: taken-action and next-state features computed a chunk
at a time from stored observations, never held for the whole dataset."""

from __future__ import annotations

import numpy as np

from ._finite import Origin, map_origin
from .fields import Field, _as_float64
from .memory import ArrayField
from .next_states import NextStates


class MappedField(Field):
    """Taken-action features computed from stored observations and actions by a feature map:
    ``read(h, s, e) = feature_map(observations[h, s:e], actions[h, s:e])`` ``(n, d)``."""

    def __init__(self, observations: Field, actions: Field, feature_map, n_features: int):
        self.observations, self.actions, self.feature_map = observations, actions, feature_map
        H, K = observations.shape[:2]
        self.shape, self.dtype = (H, K, int(n_features)), np.dtype(np.float64)

    def origin(self, name):
        return map_origin("taken-action features")

    def read(self, h, start=0, stop=None, out=None):
        obs = self.observations.read(h, start, stop)
        act = np.asarray(self.actions.read(h, start, stop), dtype=np.int64)
        out = np.asarray(self.feature_map(obs, act), dtype=np.float64)
        if out.shape != (obs.shape[0], self.shape[2]):
            raise ValueError(f"feature_map returned shape {out.shape} for {obs.shape[0]} "
                             f"observations; expected (n, d) = ({obs.shape[0]}, {self.shape[2]})")
        return out

    def lazy(self):
        return np.stack([self.read(h) for h in range(self.shape[0])])

    def take(self, idx):
        return self.lazy()[:, idx]

    def subset(self, idx, name):
        return MappedField(ArrayField(self.observations.take(idx)),
                           ArrayField(self.actions.take(idx)), self.feature_map, self.shape[2])


class MapNext(NextStates):
    """Stored next observations ``(H, K, ...)`` and a feature map evaluated chunk by chunk.

    ``feature_map(observations (n, ...), actions (n,)) -> (n, d)``; ``known_values``, when
    given, maps next observations ``(n, ...)`` to known action values ``(n, A)`` (NaN: learn).
    """

    def __init__(self, observations: Field, feature_map, n_actions: int, n_features: int,
                 known_values=None):
        self.observations, self.feature_map = observations, feature_map
        self.n_actions, self.n_features = int(n_actions), int(n_features)
        self.known_values = known_values
        self.has_known_values = known_values is not None
        self.nonnegative = None

    def origin(self, known=False):
        if not known:
            return map_origin("features of the next observations")
        if isinstance(self.known_values, Field):
            return self.known_values.origin("next_values")
        return Origin("the next_values function", "make it return finite values, or NaN "
                      "where the value must be learned")

    def features(self, h, start=0, stop=None):
        obs = self.observations.read(h, start, stop)
        n = obs.shape[0]
        out = np.empty((n, self.n_actions, self.n_features))
        for a in range(self.n_actions):
            f = np.asarray(self.feature_map(obs, np.full(n, a)), dtype=float)
            if f.shape != (n, self.n_features):
                raise ValueError(
                    f"feature_map returned shape {f.shape} for {n} next observations; "
                    f"expected (n, d) = ({n}, {self.n_features})")
            out[:, a] = f
        return out

    def known(self, h, start=0, stop=None):
        if self.known_values is None:
            return None
        if isinstance(self.known_values, Field):  # stored known values (H, K, A)
            return _as_float64(self.known_values.read(h, start, stop))
        obs = self.observations.read(h, start, stop)
        kv = np.asarray(self.known_values(obs), dtype=float)
        if kv.shape != (obs.shape[0], self.n_actions):
            raise ValueError(f"known_values returned shape {kv.shape}, expected (n, A)")
        return kv

    def take(self, idx):
        kv = self.known_values
        if isinstance(kv, Field):
            kv = ArrayField(kv.take(idx))
        return MapNext(ArrayField(self.observations.take(idx)), self.feature_map,
                       self.n_actions, self.n_features, kv)
