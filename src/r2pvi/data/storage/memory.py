"""Memory: a field held in a NumPy array."""

from __future__ import annotations

import numpy as np

from ._finite import Origin, array_origin
from .fields import Field


class ArrayField(Field):
    """A field held in a NumPy array (kept as a read-only view; never copied); ``origin``
    names where its numbers came from when not the caller (rows taken from a file)."""

    def __init__(self, array: np.ndarray, origin: Origin | None = None):
        view = array.view() if isinstance(array, np.ndarray) else np.asarray(array)
        view.flags.writeable = False
        self.array = view
        self.shape, self.dtype = view.shape, view.dtype
        self._origin = origin

    def origin(self, name):
        return array_origin(name) if self._origin is None else self._origin

    def read(self, h, start=0, stop=None):
        return self.array[h, start:stop]

    def lazy(self):
        return self.array

    def take(self, idx):
        return self.array[:, idx]
