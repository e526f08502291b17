"""The on-disk format's names and primitives: the manifest, ``.npy`` headers, the Gram
matrices written with the features, atomic creation of a dataset directory."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import socket
import uuid
from pathlib import Path

import numpy as np

from ..._io import DATASET_DIRECTORY, DATASET_KIND, EMPTY_DIRECTORY, check_replaceable
from .fields import CHUNK

# The newest format this r2pvi reads. Version 3 adds state features stored once per
# observation ("phi": "state_features"); a dataset of another kind is still written as
# version 2 (BASE_FORMAT_VERSION), so readers of version 2 keep reading it, and refuse a
# state-feature dataset by its version (asking for a newer r2pvi) instead of misreading it.
FORMAT_VERSION = 3
BASE_FORMAT_VERSION = 2
STATE_FORMAT_VERSION = 3
KIND = DATASET_KIND
MANIFEST = "manifest.json"
GRAM_FILE = "gram.npy"  # (H, d, d) float64 Phi_h^T Phi_h of the stored features (optional)
SUMS_FILE = "phi_sums.npy"  # (H, d) float64 Phi_h^T 1, the column sums (optional)


# A save writes ``.NAME.tmp-PID-HOST-RAND`` next to ``NAME`` and renames it into place; an
# overwrite moves the old dataset to ``.NAME.old-PID-HOST-RAND`` for the moment of the swap.
# HOST is a hash of the host name (temporaries on a shared file system belong to a process
# on one host: only that host can tell whether it is alive).
_HOST = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:8]
# What a dataset save may replace (see r2pvi._io.what_is_at): a dataset directory holding
# only its own files, a dataset .npz file (the single-file format), an empty directory.
REPLACEABLE = frozenset({DATASET_DIRECTORY, EMPTY_DIRECTORY, "OfflineDataset"})


def check_target(path: Path, overwrite: bool) -> None:
    """A ``FileExistsError`` unless a dataset may be saved at ``path`` (see
    :data:`REPLACEABLE`); checked before any work and again at the rename, each time after
    :func:`clean_stale` (which may put back the dataset of an interrupted overwrite)."""
    clean_stale(path)
    check_replaceable(path, REPLACEABLE, "a dataset", overwrite=overwrite)


def _side_name(path: Path, what: str) -> Path:
    return path.parent / f".{path.name}.{what}-{os.getpid()}-{_HOST}-{uuid.uuid4().hex[:8]}"


def _temp_dir(path: Path) -> Path:
    tmp = _side_name(path, "tmp")
    tmp.mkdir(parents=True)
    return tmp


def _alive(pid: int, host: str | None) -> bool:
    """Whether process ``pid`` may still be running (True whenever it cannot be told: another
    host, another user's process, a platform without a harmless liveness probe)."""
    if (host is not None and host != _HOST) or os.name != "posix" or pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)  # signal 0: no signal sent, only the existence check
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, another user's
        return True
    return True


def _stale(path: Path):
    """``(kind, side path)`` of the temporaries of saves to ``path`` whose process is gone
    (killed before it could remove them): ``kind`` is "tmp" or "old"."""
    pattern = re.compile(re.escape(f".{path.name}.") + r"(tmp|old)-(\d+)-(?:([0-9a-f]{8})-)?"
                         r"[0-9a-f]{8}$")
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return
    for entry in entries:
        m = pattern.match(entry.name)
        if m and not _alive(int(m.group(2)), m.group(3)):
            yield m.group(1), Path(entry.path)


def clean_stale(path: Path) -> None:
    """Remove what saves to ``path`` killed part-way (kill -9, power loss) left next to it:
    temporary directories of processes that are gone, and the replaced dataset of an
    interrupted overwrite, which is put back at ``path`` if the new one never got there (a
    failed save keeps the old dataset). Temporaries of live processes (or whose process
    cannot be checked) are left alone; nothing here ever raises (a read-only directory, a
    race with another cleaner)."""
    for kind, side in sorted(_stale(path)):  # "old" before "tmp"
        try:
            if kind == "old" and not os.path.lexists(path):
                os.replace(side, path)
            elif side.is_dir() and not side.is_symlink():
                shutil.rmtree(side)
            else:
                side.unlink()
        except OSError:
            pass


def _finish(tmp: Path, path: Path, manifest: dict, overwrite: bool) -> Path:
    with open(tmp / MANIFEST, "w") as fh:
        json.dump(manifest, fh, indent=1, sort_keys=True)
    try:
        check_target(path, overwrite)  # again: the path may have changed meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not os.path.lexists(path):
        os.replace(tmp, path)  # atomic: readers see the old state or the complete dataset
        return path
    old = _side_name(path, "old")
    os.replace(path, old)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.replace(old, path)  # a failed save keeps the old dataset
        raise
    if old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    else:  # a dataset .npz file (the single-file format) replaced by the directory
        old.unlink(missing_ok=True)
    return path


def _add_gram(gram: np.ndarray, rows: np.ndarray, sums: np.ndarray,
              row_sums: list | None = None) -> None:
    """``gram += X^T X`` and ``sums += X^T 1`` for rows ``X (n, d)`` in float64 (by blocks of
    ``CHUNK`` rows); ``row_sums`` (``[low, high]``, if given) widened to the range of the rows'
    sums ``X 1`` (the manifest's ``phi_row_sums``)."""
    for s in range(0, rows.shape[0], CHUNK):
        x = np.asarray(rows[s:s + CHUNK], dtype=np.float64)
        gram += x.T @ x
        sums += np.ones(x.shape[0]) @ x
        if row_sums is not None and x.shape[0]:
            rs = x @ np.ones(x.shape[1])
            row_sums[0] = min(row_sums[0], float(rs.min()))
            row_sums[1] = max(row_sums[1], float(rs.max()))


def manifest_range(mf: dict, key: str) -> tuple[float, float] | None:
    """A ``[low, high]`` pair the manifest records under ``key`` (``reward_range``,
    ``phi_row_sums``), or None when it is absent (written before it) or not a finite
    ordered pair (then the facts are found from the data instead)."""
    rs = mf.get(key)
    if (isinstance(rs, list) and len(rs) == 2
            and all(isinstance(x, int | float) and not isinstance(x, bool) for x in rs)
            and np.isfinite(rs).all() and rs[0] <= rs[1]):
        return float(rs[0]), float(rs[1])
    return None
