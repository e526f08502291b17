"""Memory: a field held in a NumPy array."""

from __future__ import annotations

import numpy as np

from ._finite import Origin, array_origin, subset_origin
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

    def read(self, h, start=0, stop=None, out=None):
        return self.array[h, start:stop]

    def lazy(self):
        return self.array

    def take(self, idx):
        return self.array[:, idx]

    def subset(self, idx, name):
        return in_memory(self, idx, name)

    def step_rows(self, h, chunk, out=None):
        if self.dtype == np.float64 or out is None:
            return np.ascontiguousarray(self.read(h), dtype=np.float64)
        shape = self.shape[1:]
        if out.shape != shape or out.dtype != np.float64:
            out = np.empty(shape)
        np.copyto(out, self.read(h))
        return out

    def float64_array(self):
        a = self.array
        return a if a.dtype == np.float64 and a.flags.c_contiguous else None

    def times(self, h, z, chunk):
        if self.dtype == np.float64:
            return self.read(h) @ z
        return super().times(h, z, chunk)


def in_memory(field: Field, idx: np.ndarray, name: str) -> ArrayField:
    """The trajectories ``idx`` of ``field`` read into memory; its errors name where the
    numbers came from (the selection's trajectory numbers)."""
    return ArrayField(field.take(idx), subset_origin(field.origin(name)))
