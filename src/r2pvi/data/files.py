"""Saving, opening and loading an :class:`~r2pvi.OfflineDataset`: a dataset directory (the
on-disk format of :mod:`~r2pvi.data.storage`) or the legacy single-file ``.npz`` format.
``save`` is bound to ``OfflineDataset`` as a method, ``open`` and ``load`` as classmethods."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._io import file_error, load_npz, save_npz
from . import storage as _st
from .storage.behaviour import _next_form
from .storage.fields import _float_dtype

__all__ = ["save", "open_dataset", "load"]

DATASET_FORMAT_VERSION = 1  # the legacy single-file .npz format (still read and written)


def save(self, path, *, dtype=None, overwrite: bool = False,
         next_form: str = "full") -> Path:
    """Save in the on-disk format: a directory of step-major ``.npy`` files and a JSON
    manifest (format version 2; 3 for episodes stored as state features, which keep that
    layout: ``psi.npy`` once per observation), written in a temporary directory and renamed
    into place. A path ending in ``.npz`` writes the legacy single-file format (version 1),
    atomically too. An existing path is refused unless ``overwrite=True``, and then too
    unless it holds an r2pvi dataset (a dataset directory holding only its own files, a
    dataset ``.npz`` file) or nothing (an empty directory; an empty file for an ``.npz``
    path): a ``FileExistsError`` names what is there, so a save never destroys a file or
    directory r2pvi did not write. A failed save keeps the previous dataset. Returns the
    path written. Open it lazily with :meth:`open` (any size).

    ``next_form="behaviour"`` stores the next-state features without each sample's row
    that equals the next step's taken-action features ``phi[k, h+1]`` (see
    :class:`~r2pvi.DatasetWriter`); the fits are bitwise the same.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from r2pvi import OfflineDataset
    >>> ds = OfflineDataset.from_features(np.ones((2, 1, 1)), np.zeros((2, 1)),
    ...                                   np.ones((2, 1, 1, 1)))
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     p = ds.save(os.path.join(tmp, "data"))
    ...     sorted(os.listdir(p)), OfflineDataset.open(p).n_trajectories
    (['gram.npy', 'manifest.json', 'next_phi.npy', 'phi.npy', 'phi_sums.npy', 'rewards.npy'], 2)
    """
    p = Path(os.fspath(path))
    if not self._source.dense_rows:  # before any check of the path: nothing is touched
        raise TypeError(f"cannot save a dataset of sparse rows to {path}: saving sparse rows "
                        "is not supported (the on-disk format stores dense rows); keep the "
                        "feature map and the observations, and rebuild it with "
                        "OfflineDataset.from_episodes or r2pvi.sparse.SparseOfflineDataset"
                        ".from_transitions")
    next_form = _next_form(next_form)
    if p.suffix == ".npz":
        if next_form != "full":
            raise ValueError("the legacy .npz format stores next_phi whole: use a "
                             "directory path for next_form='behaviour'")
        return _save_npz(self, p, overwrite)
    dtype = None if dtype is None else _float_dtype(dtype)
    return _st.write_directory(self._source, p, dtype=dtype, overwrite=overwrite,
                               next_form=next_form)


def _save_npz(self, path, overwrite: bool = False):
    """The legacy single-file format (version 1) of ``self`` at ``path``."""
    arrays = {
        "phi": self.phi,
        "rewards": self.rewards,
        "next_phi": self.next_phi,
        "next_values": self.next_values,
    }
    for key, value in self._extras.items():
        value = np.asarray(value)
        if value.dtype == object:
            raise TypeError(f"cannot save {key!r}: object arrays are not supported")
        arrays["extra_" + key] = value
    meta = {"reward_noise": self.reward_noise} if self.reward_noise else {}
    if self.stationary:
        meta["stationary"] = True
    if self._source.reward_offset:
        meta["reward_offset"] = self._source.reward_offset
    return save_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION, arrays, meta,
                    overwrite=overwrite)


def open_dataset(cls, path, *, feature_map=None):
    """Open a dataset directory written by :meth:`save` or :class:`~r2pvi.DatasetWriter`
    lazily: only the headers are read; a fit reads one step at a time, in chunks.
    ``feature_map`` is needed (and only then) for a dataset stored as observations
    (see :meth:`from_observations`)."""
    return cls(_source=_st.open_directory(path, feature_map))


def load(cls, path):
    """Load a dataset written by :meth:`save` into memory: a directory (format 2) or a
    legacy ``.npz`` file (format 1)."""
    p = Path(os.fspath(path))
    if p.is_dir():
        src = _st.open_directory(p)
        return cls(_source=src.take(np.arange(src.n_trajectories)))
    arrays, header = load_npz(path, "OfflineDataset", DATASET_FORMAT_VERSION)
    known = {"phi", "rewards", "next_phi", "next_values"}
    known |= {"extra_" + k for k in ("states", "actions", "next_states")}
    for name in sorted(known - set(arrays)):
        if not name.startswith("extra_"):
            raise file_error(path, name, "is missing")
    unknown = sorted(set(arrays) - known)
    if unknown:
        raise file_error(path, unknown[0], "is not a field of an OfflineDataset file")
    extras = {k[len("extra_") :]: v for k, v in arrays.items() if k.startswith("extra_")}
    try:  # the loaded arrays go through the same checks as from_features
        ds = cls.from_features(
            arrays["phi"],
            arrays["rewards"],
            arrays["next_phi"],
            arrays["next_values"],
            check_simplex=False,
            reward_noise=header.get("reward_noise", 0.0),
            **extras,
        )
    except (TypeError, ValueError) as exc:
        raise file_error(path, None, f"holds invalid data: {exc}") from None
    ds._source.stationary = header.get("stationary", False) is True
    offset = header.get("reward_offset", 0.0)
    if isinstance(offset, int | float) and not isinstance(offset, bool) and offset >= 0:
        ds._source.reward_offset = float(offset)
    return ds
