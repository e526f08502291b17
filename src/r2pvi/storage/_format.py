"""The on-disk format's names and primitives: the manifest, ``.npy`` headers, the Gram
matrices written with the features, atomic creation of a dataset directory."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from ._fields import CHUNK

FORMAT_VERSION = 2
FIRST_DIRECTORY_VERSION = 2  # format 1 is the legacy single-file .npz
KIND = "r2pvi.OfflineDataset"
MANIFEST = "manifest.json"
GRAM_FILE = "gram.npy"  # (H, d, d) float64 Phi_h^T Phi_h of the stored features (optional)
SUMS_FILE = "phi_sums.npy"  # (H, d) float64 Phi_h^T 1, the column sums (optional)


def _manifest(path: Path) -> dict:
    mf = path / MANIFEST
    if not mf.is_file():
        raise ValueError(f"{path} is not an r2pvi dataset directory (no {MANIFEST})")
    with open(mf) as fh:
        header = json.load(fh)
    if header.get("kind") != KIND:
        raise ValueError(f"{path} holds a {header.get('kind')!r}, not a {KIND!r}")
    version = header.get("format_version")
    if (isinstance(version, bool) or not isinstance(version, int)
            or version < FIRST_DIRECTORY_VERSION):
        # dataset directories exist from format version 2 on: anything else is not one
        raise ValueError(
            f"{path}: the manifest's format_version must be an integer >= "
            f"{FIRST_DIRECTORY_VERSION} (the dataset directory format), got {version!r}; the "
            "manifest is damaged or was not written by r2pvi"
        )
    if version > FORMAT_VERSION:
        raise ValueError(
            f"{path} has format version {version}; this r2pvi reads version "
            f"{FORMAT_VERSION}: upgrade r2pvi"
        )
    return header


def _temp_dir(path: Path) -> Path:
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    return tmp


def _finish(tmp: Path, path: Path, manifest: dict, overwrite: bool) -> Path:
    with open(tmp / MANIFEST, "w") as fh:
        json.dump(manifest, fh, indent=1, sort_keys=True)
    if path.exists():
        if not overwrite:
            shutil.rmtree(tmp, ignore_errors=True)
            raise FileExistsError(f"{path} exists; pass overwrite=True or choose a new path")
        old = path.parent / f".{path.name}.old-{uuid.uuid4().hex[:8]}"
        was_dir = path.is_dir()
        os.replace(path, old)
        os.replace(tmp, path)
        if was_dir:
            shutil.rmtree(old, ignore_errors=True)
        else:  # a file (a legacy .npz, say) replaced by the directory
            old.unlink(missing_ok=True)
    else:
        os.replace(tmp, path)  # atomic: readers see the old state or the complete dataset
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


def _write_npy_header(fh, shape, dtype):
    np.lib.format.write_array_header_2_0(
        fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
             "shape": tuple(int(s) for s in shape)})
