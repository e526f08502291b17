"""Versioned ``.npz`` files with an embedded JSON header (never pickles).

Saves are atomic: the archive is written to a temporary file in the target's directory and
moved over the target with :func:`os.replace`, so a save that fails part-way (disk full, a
file-size limit, an exception) leaves any previous file intact. Loads check everything they
read and report a bad file as a ``ValueError`` naming the file and the field.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path

import numpy as np

__all__ = ["save_npz", "load_npz", "FileFieldError", "file_array", "file_error",
           "check_replaceable", "what_is_at"]

_META_KEY = "__r2pvi_meta__"
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


class FileFieldError(ValueError):
    """A saved file is unreadable or one of its fields is invalid (names file and field)."""


def file_error(path, field: str | None, problem: str) -> FileFieldError:
    """The error for a bad ``field`` (None: the file as a whole) of the file at ``path``."""
    where = f"{path}" if field is None else f"{path}: field {field!r}"
    return FileFieldError(f"{where} {problem}")


# What each kind of file holds and how to read it (for errors that name the right loader).
_KINDS = {
    "estimator": ("an estimator", "r2pvi.load(path) (or the estimator class's load)"),
    "OfflineDataset": ("a dataset", "r2pvi.OfflineDataset.load(path)"),
    "feature_map": ("a feature map", "r2pvi.features.load_feature_map(path)"),
}


def _what(kind) -> str:
    return _KINDS[kind][0] if kind in _KINDS else f"a {kind!r}"


def _held_kind(path: Path):
    """The kind recorded in an existing r2pvi ``.npz`` file's header (reading that entry
    only), or None when the file is not one."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            if _META_KEY not in npz.files:
                return None
            kind = json.loads(str(npz[_META_KEY])).get("kind")
    except Exception:  # not a zip archive, damaged, not JSON, not a dict: not r2pvi's
        return None
    return kind if isinstance(kind, str) else None


# What may stand at a path a save replaces (besides r2pvi ``.npz`` kinds, see _KINDS).
DATASET_KIND = "r2pvi.OfflineDataset"  # the "kind" of a dataset directory's manifest.json
DATASET_DIRECTORY = "<an r2pvi dataset directory>"
EMPTY_DIRECTORY = "<an empty directory>"
EMPTY_FILE = "<an empty file>"
_LISTED = 5  # foreign entries named in an error


def _dataset_directory_files(path: Path) -> set[str] | None:
    """The entries an r2pvi dataset directory ``path`` is made of (``manifest.json``, the
    files its manifest lists, ``extra_<name>.npy``), or None when ``path`` has no readable
    dataset manifest."""
    try:
        with open(path / "manifest.json", "rb") as fh:
            header = json.loads(fh.read(1 << 20))
    except (OSError, ValueError):  # missing, unreadable, not JSON (UnicodeDecodeError too)
        return None
    if not isinstance(header, dict) or header.get("kind") != DATASET_KIND:
        return None
    files, extras = header.get("files"), header.get("extras", [])
    if (not isinstance(files, dict) or not isinstance(extras, list)
            or not all(isinstance(f, str) for f in files.values())
            or not all(isinstance(e, str) for e in extras)):
        return None
    return {"manifest.json", *files.values(), *(f"extra_{e}.npy" for e in extras)}


def what_is_at(path) -> tuple[str, str]:
    """``(description, kind)`` of what exists at ``path``: ``kind`` is an r2pvi ``.npz``
    file's kind, :data:`DATASET_DIRECTORY` (a directory holding exactly the files of an r2pvi
    dataset), :data:`EMPTY_DIRECTORY`, :data:`EMPTY_FILE`, or ``""`` for anything else
    (a file or directory r2pvi did not write, a link, a device)."""
    path = Path(os.fspath(path))
    if path.is_symlink():
        return f"a symbolic link (to {os.readlink(path)})", ""
    if path.is_dir():
        try:
            entries = sorted(e.name for e in path.iterdir())
        except OSError as exc:
            return f"a directory r2pvi cannot list ({exc.strerror})", ""
        if not entries:
            return "an empty directory", EMPTY_DIRECTORY
        own = _dataset_directory_files(path)
        foreign = entries if own is None else [e for e in entries if e not in own]
        if not foreign:
            return "an r2pvi dataset directory", DATASET_DIRECTORY
        names = ", ".join(foreign[:_LISTED]) + (", ..." if len(foreign) > _LISTED else "")
        count = f"{len(foreign)} {'entry' if len(foreign) == 1 else 'entries'}"
        if own is None:
            return (f"a directory that is not an r2pvi dataset (no valid manifest.json; "
                    f"{count}: {names})"), ""
        return (f"an r2pvi dataset directory that also holds {count} r2pvi did not write "
                f"({names})"), ""
    if path.is_file():
        if path.stat().st_size == 0:
            return "an empty file", EMPTY_FILE
        held = _held_kind(path)
        if held is None:
            return "a file r2pvi did not write", ""
        return f"{_what(held)} (kind {held!r})", held
    return "something that is neither a file nor a directory", ""


def check_replaceable(path, replaceable, saving: str, *, overwrite: bool) -> None:
    """Refuse to save ``saving`` (e.g. "a dataset") at an existing ``path``: always with
    ``overwrite=False``, and with ``overwrite=True`` unless what is there (see
    :func:`what_is_at`) has one of the kinds in ``replaceable``. A ``FileExistsError``
    naming the path and what it holds; nothing is done when ``path`` does not exist."""
    path = Path(os.fspath(path))
    if not os.path.lexists(path):
        return
    if not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True or choose a new path")
    description, kind = what_is_at(path)
    if kind not in replaceable:
        raise FileExistsError(
            f"{path} exists and holds {description}: saving {saving} there would destroy "
            "it; choose another path or remove it first")


def save_npz(path, kind: str, version: int, arrays: dict[str, np.ndarray], meta: dict,
             *, overwrite: bool = True) -> Path:
    """Write ``arrays`` and a JSON header ``{"kind", "format_version", **meta}`` to ``path``.

    The write goes to a temporary file next to ``path``, then replaces ``path`` atomically.
    ``path`` gets the suffix ``.npz`` when it has none. A directory is never written over.
    An existing file is refused with ``overwrite=False``, and with ``overwrite=True`` too
    unless it is an r2pvi file of the same ``kind`` or empty (a model replaces a model; a
    save never destroys a dataset or a file r2pvi did not write): see :func:`check_replaceable`.
    """
    given = Path(os.fspath(path))
    path = given if given.suffix == ".npz" else given.with_name(given.name + ".npz")
    if given.is_dir() or path.is_dir():
        where = given if given.is_dir() else path
        what = (" (an r2pvi dataset directory)" if (where / "manifest.json").is_file()
                else "")
        suggestion = where.with_name(where.stem + "-" + kind.lower() + ".npz") if (
            where.suffix == ".npz") else where.with_name(where.name + ".npz")
        raise IsADirectoryError(
            f"cannot save to {where}: it is a directory{what}; {_what(kind)} is saved to one "
            f".npz file: pass a file path such as {str(suggestion)!r}")
    check_replaceable(path, {kind, EMPTY_FILE}, _what(kind), overwrite=overwrite)
    header = {"kind": kind, "format_version": version, **meta}
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    if _META_KEY in payload:
        raise ValueError(f"array name {_META_KEY!r} is reserved")
    payload[_META_KEY] = np.array(json.dumps(header, sort_keys=True))
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    try:
        with open(tmp, "xb") as fh:  # honours the umask, like a plain open(path, "wb")
            np.savez_compressed(fh, **payload)  # type: ignore[arg-type]
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            _place_new(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def _place_new(tmp: Path, path: Path) -> None:
    """Move ``tmp`` to ``path`` only if ``path`` does not exist, atomically where the file
    system has hard links (a file created meanwhile is never replaced)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; pass overwrite=True or choose a new path") from None
    except OSError:  # no hard links here (some network or FAT file systems)
        if path.exists():
            raise FileExistsError(f"{path} exists; pass overwrite=True or choose a new path") \
                from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def _read(path: Path) -> tuple[dict[str, np.ndarray], str]:
    """Every array of the archive and the raw header text; bad archives -> FileFieldError."""
    if path.is_dir():
        if (path / "manifest.json").is_file():
            raise file_error(path, None, "is a dataset directory, not an r2pvi .npz file: "
                             "open it with r2pvi.OfflineDataset.open(path) (lazily) or "
                             "r2pvi.OfflineDataset.load(path) (into memory)")
        raise file_error(path, None, "is a directory, not an r2pvi .npz file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if not magic:
        raise file_error(path, None, "is empty (0 bytes): not an r2pvi .npz file")
    if magic not in _ZIP_MAGIC:
        raise file_error(path, None, "is not an r2pvi .npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            if _META_KEY not in npz.files:
                raise file_error(path, _META_KEY, "is missing: not an r2pvi file")
            meta = npz[_META_KEY]
            arrays = {k: npz[k] for k in npz.files if k != _META_KEY}
    except FileFieldError:
        raise
    except ValueError as exc:  # object arrays (pickles) are refused by allow_pickle=False
        raise file_error(path, None, f"holds an array r2pvi cannot read safely: {exc}") from None
    except Exception as exc:  # BadZipFile, zlib.error, EOFError, OSError, NotImplementedError
        # (an unknown compression method), RuntimeError (encrypted), MemoryError, ...
        raise file_error(
            path, None, f"is damaged or truncated ({type(exc).__name__}: {exc})"
        ) from None
    if meta.ndim != 0 or meta.dtype.kind != "U":
        raise file_error(path, _META_KEY, "must be a JSON string")
    return arrays, str(meta)


def load_npz(path, kind: str, max_version: int) -> tuple[dict[str, np.ndarray], dict]:
    """Read a file written by :func:`save_npz`, checking its kind and format version."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise FileNotFoundError(f"no such file: {path}")
    arrays, text = _read(path)
    try:
        header = json.loads(text)
    except json.JSONDecodeError as exc:
        raise file_error(path, "header", f"is not valid JSON: {exc}") from None
    if not isinstance(header, dict):
        raise file_error(path, "header", f"must be a JSON object, got {type(header).__name__}")
    held = header.get("kind")
    if held != kind:
        if held in _KINDS:
            raise file_error(path, "kind", f"is {held!r}: the file holds {_what(held)}, not "
                             f"{_what(kind)}; load it with {_KINDS[held][1]}")
        raise file_error(path, "kind", f"is {held!r}: the file does not hold {_what(kind)}")
    version = header.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise file_error(path, "format_version", f"must be an integer >= 1, got {version!r}")
    if version > max_version:
        raise file_error(
            path, "format_version",
            f"says format version {version}; this r2pvi reads versions <= {max_version}: "
            "upgrade r2pvi",
        )
    return arrays, header


def file_array(path, arrays: dict, name: str, *, ndim: int | None = None,
               shape: tuple | None = None, allow_nan: bool = False) -> np.ndarray:
    """The float array ``name`` of a loaded file, checked (present, numeric, shape, finite)."""
    if name not in arrays:
        raise file_error(path, name, "is missing")
    arr = arrays[name]
    if arr.dtype.kind not in "biuf":
        raise file_error(path, name, f"must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if ndim is not None and arr.ndim != ndim:
        raise file_error(path, name, f"must have {ndim} dimensions, got shape {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise file_error(path, name, f"must have shape {shape}, got {arr.shape}")
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        raise file_error(path, name, f"has {int(bad.sum())} NaN or infinite entries")
    return arr
