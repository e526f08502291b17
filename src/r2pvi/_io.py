"""Versioned ``.npz`` files with an embedded JSON header (never pickles)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

_META_KEY = "__r2pvi_meta__"


def save_npz(path, kind: str, version: int, arrays: dict[str, np.ndarray], meta: dict) -> Path:
    """Write ``arrays`` and a JSON header ``{"kind", "format_version", **meta}`` to ``path``."""
    path = Path(os.fspath(path))
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    header = {"kind": kind, "format_version": version, **meta}
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    if _META_KEY in payload:
        raise ValueError(f"array name {_META_KEY!r} is reserved")
    payload[_META_KEY] = np.array(json.dumps(header, sort_keys=True))
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **payload)  # type: ignore[arg-type]
    return path


def load_npz(path, kind: str, max_version: int) -> tuple[dict[str, np.ndarray], dict]:
    """Read a file written by :func:`save_npz`, checking its kind and format version."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise FileNotFoundError(f"no such file: {path}")
    with np.load(path, allow_pickle=False) as npz:
        if _META_KEY not in npz.files:
            raise ValueError(f"{path} is not an r2pvi file (no {_META_KEY} header)")
        header = json.loads(str(npz[_META_KEY]))
        arrays = {k: npz[k] for k in npz.files if k != _META_KEY}
    if header.get("kind") != kind:
        raise ValueError(f"{path} holds a {header.get('kind')!r}, not a {kind!r}")
    version = header.get("format_version")
    if not isinstance(version, int) or version > max_version:
        raise ValueError(
            f"{path} has format version {version!r}; this r2pvi reads versions <= {max_version}: "
            "upgrade r2pvi"
        )
    return arrays, header
