"""State features in a dataset directory: ``psi`` once per observation, actions by index.

The directory form of :mod:`~r2pvi.data.storage.crossed` (format version 3, ``"phi":
"state_features"`` and ``"next": "state_features"`` in the manifest, with
``n_state_features`` m and ``n_features = n_actions m``):

- ``psi.npy (H+1, K, m)`` float32 or float64: row ``h`` holds observation ``h`` of each
  episode (the state of step ``h`` and the next state of step ``h - 1``);
- ``actions.npy (H, K)`` signed integers (int8 up to 127 actions): the taken action's index,
  ``-1`` where a step carries no data;
- ``rewards.npy (H, K)`` and the optional ``next_values.npy (H, K, A)`` as in the other
  kinds.

:func:`open_state_features` memory-maps ``psi`` and ``actions`` into a
:class:`StateFileField` and a :class:`~r2pvi.data.storage.crossed.CrossedNext` over the same
map, so that pooled fits read ``psi`` from the page cache
(:meth:`~r2pvi.data.storage.source.StepSource.pooled_crossed`). Fits of this kind do not
check ``psi`` as they read it (the pooled products never form the rows), so opening reads
``psi``, ``actions`` and ``next_values`` once and checks every number (``m + 1 + A`` numbers
per transition; the other kinds' fits check theirs as they read them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..._io import file_error
from ._finite import file_origin
from .behaviour import _action_dtype
from .crossed import CrossedField, CrossedNext
from .fields import Field
from .memory import ArrayField

__all__ = ["StateFileField", "is_state_layout", "open_state_features", "write_state_features"]

STATE = "state_features"  # the manifest's "phi" and "next" of this kind
_FIX = "the dataset is damaged: write the dataset again from its source"
# Rows of (H+1) K (psi) or H K (actions, known values) scanned per chunk at open.
_SCAN_ROWS = 1 << 16


class StateFileField(CrossedField):
    """:class:`~r2pvi.data.storage.crossed.CrossedField` over the memory-mapped ``psi.npy``
    and ``actions.npy`` of a dataset directory (its errors name ``psi.npy``; a subset is in
    memory)."""

    storage = "disk"

    def __init__(self, psi: np.ndarray, actions: np.ndarray, n_actions: int, path: Path):
        super().__init__(psi, actions, n_actions)
        self.path = Path(path)

    def origin(self, name):
        return file_origin(self.path)


def is_state_layout(source) -> bool:
    """Whether ``source`` (a :class:`~r2pvi.data.storage.source.StepSource`) holds state
    features stored once per observation."""
    return isinstance(source.phi, CrossedField) and isinstance(source.next, CrossedNext)


# ---------------------------------------------------------------------- writing
def write_state_features(source, put, store: np.dtype, meta: dict) -> None:
    """Write ``psi`` (in ``store``) and ``actions`` of ``source`` with ``put(name, field,
    dtype)`` (streamed, as the directory writer writes every field), the known values when
    there are any, and the kind's manifest keys (besides "phi" and "next") into ``meta``."""
    phi, nxt = source.phi, source.next
    if nxt.psi is not phi.psi and not _same(nxt.psi, phi.psi):
        raise ValueError("this dataset's next-state rows do not read the state features of "
                         "its taken-action rows: it cannot be saved in the state-feature "
                         "layout (build it with OfflineDataset.from_episodes)")
    put("psi", ArrayField(phi.psi), store)
    put("actions", ArrayField(phi.actions), _action_dtype(phi.n_actions))
    if nxt.has_known_values:
        put("next_values", nxt.next_values, np.float64)
    meta.update({"n_state_features": int(phi.psi.shape[2]),
                 "nonnegative_next_phi": nxt.nonnegative})


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two ``psi`` arrays hold the same numbers (compared by step)."""
    return a.shape == b.shape and all(np.array_equal(a[t], b[t]) for t in range(a.shape[0]))


# ---------------------------------------------------------------------- opening
def open_state_features(path: Path, mf: dict, field, known: Field | None) -> StateFileField:
    """The taken-action field of the state-feature dataset at ``path`` (manifest ``mf``,
    already checked; ``field(name, kinds, dtype)`` gives a file's header-checked
    :class:`~r2pvi.data.storage.files.FileField`; ``known`` the known values' field or None);
    its next-state form is ``CrossedNext(field.psi, ...)``. Every number of ``psi``,
    ``actions`` and ``known`` is checked here."""
    A = mf["n_actions"]
    store = np.dtype(mf.get("dtype", "float64"))
    psi_file = field("psi", "f", store)
    act_file = field("actions", "iu")
    psi = _mapped(psi_file)
    actions = _mapped(act_file)
    _check_actions(act_file.path, actions, A)
    _check_finite(psi_file.path, "psi", psi, "observation", "feature")
    if known is not None:
        _check_finite(known.path, "next_values", _mapped(known), "step", "action",
                      allow_nan=True)
    return StateFileField(psi, actions, A, psi_file.path)


def _mapped(f) -> np.ndarray:
    """The file of the field ``f`` memory-mapped read-only, as a plain ndarray view."""
    arr = np.asarray(f.lazy())
    arr.flags.writeable = False
    return arr


def _scan(arr: np.ndarray, bad):
    """``(index, value)`` of the first entry of ``arr`` where ``bad(chunk)`` is True (in C
    order, read by chunks of rows of its first two axes), or None."""
    lead = arr.shape[0] * arr.shape[1]
    flat = arr.reshape((lead,) + arr.shape[2:])
    for s in range(0, lead, _SCAN_ROWS):
        hit = np.flatnonzero(bad(flat[s:s + _SCAN_ROWS]))
        if hit.size:
            rest = flat.shape[1:]
            i = np.unravel_index(int(hit[0]), (min(lead, s + _SCAN_ROWS) - s,) + rest)
            row = s + int(i[0])
            index = [row // arr.shape[1], row % arr.shape[1]] + [int(j) for j in i[1:]]
            return index, arr[tuple(index)]
    return None


def _check_actions(file: Path, actions: np.ndarray, n_actions: int) -> None:
    """Every action index is ``-1`` (no data) or an action ``0 .. A-1``."""
    hit = _scan(actions, lambda a: (a < -1) | (a >= n_actions))
    if hit is not None:
        (h, k), value = hit
        raise file_error(file, "actions", f"holds {int(value)} at index [{h}, {k}] (step {h}, "
                         f"trajectory {k}): an action index must be -1 (no data) or in "
                         f"[0, n_actions = {n_actions}); {_FIX}")


def _check_finite(file: Path, name: str, arr: np.ndarray, first: str, last: str,
                  allow_nan: bool = False) -> None:
    """Every number of ``arr`` is finite (``allow_nan``: not infinite; NaN marks a value to
    learn)."""
    hit = _scan(arr, np.isinf if allow_nan else (lambda x: ~np.isfinite(x)))
    if hit is not None:
        index, value = hit
        where = f"{first} {index[0]}, trajectory {index[1]}, {last} {index[2]}"
        what = "an infinite known value" if allow_nan else "a non-finite number"
        raise file_error(file, name, f"holds {what}, {float(value)!r}, at index {index} "
                         f"({where}): a fit uses only finite numbers; {_FIX}")

