""".npy files of the on-disk format: headers read and checked, written."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..._io import FileFieldError, file_error


def npy_header(path: Path, name: str, min_ndim: int = 0,
               fortran_ok: bool = False) -> tuple[tuple, np.dtype, int]:
    """``(shape, dtype, offset of the data)`` of the ``.npy`` file of the field ``name``,
    checked: a ``.npy`` file (not empty, not an ``.npz`` or text), C-ordered (unless
    ``fortran_ok``), of real numbers (never Python objects: nothing is unpickled), with at
    least ``min_ndim`` dimensions and all the bytes its header announces. Anything else is a
    ``ValueError`` naming the file and the field."""
    def bad(problem):
        return file_error(path, name, problem + "; the dataset is damaged")

    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            head = fh.read(6)
            fh.seek(0)
            if not head:
                raise bad("is empty (0 bytes), not a .npy file")
            if head[:2] == b"PK":
                raise bad("is a zip archive (an .npz file?), not a .npy file")
            if head != b"\x93NUMPY":
                raise bad("is not a .npy file (no .npy magic string)")
            version = np.lib.format.read_magic(fh)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(fh)
            offset = fh.tell()
    except FileNotFoundError:
        raise bad("is missing") from None
    except (IsADirectoryError, PermissionError) as exc:
        raise bad(f"cannot be read ({exc.strerror})") from None
    except FileFieldError:
        raise
    except ValueError as exc:
        raise bad(f"has a damaged .npy header ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - EOFError, SyntaxError, ...: a damaged header
        raise bad(f"has a damaged .npy header ({type(exc).__name__}: {exc})") from None
    dtype = np.dtype(dtype)
    if dtype.hasobject:
        raise bad("holds Python objects (dtype object), which r2pvi never reads (no pickle)")
    if dtype.kind not in "biuf" or dtype.fields is not None:
        raise bad(f"holds {dtype} data, not real numbers")
    if fortran and len(shape) > 1 and not fortran_ok:
        raise bad("is Fortran-ordered; r2pvi writes and reads C-ordered .npy files")
    if len(shape) < min_ndim:
        raise bad(f"must have at least {min_ndim} dimensions, got shape {tuple(shape)}")
    need = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if size < need:
        raise bad(f"is truncated: {size} bytes, its header announces {need}")
    return tuple(int(x) for x in shape), dtype, offset


def load_npy(path: Path, name: str, mmap: bool = False) -> np.ndarray:
    """The whole ``.npy`` file of the field ``name`` (checked by :func:`npy_header`; either
    memory order), in memory or (``mmap=True``) memory-mapped read-only."""
    npy_header(path, name, fortran_ok=True)
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - checked above: only I/O errors remain
        raise file_error(path, name, f"cannot be read ({type(exc).__name__}: {exc})") from None


def _write_npy_header(fh, shape, dtype):
    np.lib.format.write_array_header_2_0(
        fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
             "shape": tuple(int(s) for s in shape)})
