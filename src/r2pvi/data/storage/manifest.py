"""What is checked when a dataset directory is opened: its manifest (every key, its type and
range), where its files are (inside the directory only), their shapes and dtypes against the
manifest, and the stored sums (``gram.npy``, ``phi_sums.npy``). Each problem is a
``ValueError`` naming the file and the field (:func:`r2pvi._io.file_error`)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from ..._io import file_error
from .files import FileField
from .format import FORMAT_VERSION, KIND, MANIFEST
from .npy import load_npy

FIRST_DIRECTORY_VERSION = 2  # format 1 is the legacy single-file .npz
NEXT_FIELDS = {"stored": ("next_phi",), "table": ("next_index", "next_table"),
               "map": ("next_observations",),
               "behaviour": ("next_action", "next_rest", "next_side", "next_side_offsets"),
               "state_features": ()}
PHI_FIELDS = {"stored": ("phi",), "map": ("observations", "actions"),
              "state_features": ("psi", "actions")}
# State features once per observation (storage.state_files): "phi" and "next" both
# "state_features", n_state_features = m with n_features = n_actions * m.
STATE = "state_features"
OPTIONAL_FIELDS = ("next_values", "gram", "phi_sums", "next_table_values")
# Fields read whole (no entry in "shapes"); the others are streamed by step.
WHOLE_FIELDS = ("gram", "phi_sums", "next_table", "next_table_values")
COUNTS = ("horizon", "n_trajectories", "n_features", "n_actions")
_EXTRA_NAME = re.compile(r"[A-Za-z0-9_]+")
# Stored Gram matrices are checked for positive semi-definiteness (a Cholesky factor per
# step, d^3 / 3 flops) up to this d; above it, only the O(d^2) checks of check_stored_sums.
PSD_CHECK_MAX_D = 128


def read_manifest(path: Path) -> dict:
    """The manifest of the dataset directory ``path``, every key checked."""
    mf = path / MANIFEST
    if not mf.is_file():
        raise ValueError(f"{path} is not an r2pvi dataset directory (no {MANIFEST})")

    def bad(key, problem):
        return file_error(mf, key, problem + "; the manifest is damaged or was not written "
                          "by r2pvi")

    try:
        text = mf.read_bytes()
    except OSError as exc:
        raise file_error(mf, None, f"cannot be read ({exc.strerror})") from None
    if not text.strip():
        raise file_error(mf, None, "is empty: the dataset's manifest is missing its content")
    try:
        header = json.loads(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise file_error(mf, None, f"is not valid JSON ({exc})") from None
    if not isinstance(header, dict):
        raise file_error(mf, None, f"must hold a JSON object, got a JSON "
                         f"{type(header).__name__}")
    if header.get("kind") != KIND:
        raise file_error(mf, "kind", f"is {header.get('kind')!r}, not {KIND!r}: {path} holds "
                         "no r2pvi dataset")
    version = header.get("format_version")
    if (isinstance(version, bool) or not isinstance(version, int)
            or version < FIRST_DIRECTORY_VERSION):
        raise bad("format_version", f"must be an integer >= {FIRST_DIRECTORY_VERSION} (the "
                  f"dataset directory format), got {version!r}")
    if version > FORMAT_VERSION:
        raise file_error(mf, "format_version", f"is {version}: {path} has format version "
                         f"{version}; this r2pvi reads versions {FIRST_DIRECTORY_VERSION} to "
                         f"{FORMAT_VERSION}: upgrade r2pvi")
    for key in ("files", "shapes", "next") + COUNTS:
        if key not in header:
            raise bad(key, "is missing")
    for key in COUNTS:
        value = header[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise bad(key, f"must be an integer >= 1, got {value!r}")
    _check_choice(header, "next", tuple(NEXT_FIELDS), bad)
    _check_choice(header, "phi", tuple(PHI_FIELDS), bad, "stored")
    _check_choice(header, "dtype", ("float32", "float64"), bad, "float64")
    _check_choice(header, "layout", ("step-major",), bad, "step-major")
    _check_state_keys(header, version, bad)
    for key in ("nonnegative_phi", "nonnegative_next_phi"):
        if header.get(key) is not None and not isinstance(header[key], bool):
            raise bad(key, f"must be true, false or null, got {header[key]!r}")
    extras = header.get("extras", [])
    if not isinstance(extras, list) or not all(
            isinstance(e, str) and _EXTRA_NAME.fullmatch(e) for e in extras):
        raise bad("extras", f"must be a list of names (letters, digits, _), got {extras!r}")
    _check_files(path, header, bad)
    return header


def _check_state_keys(header, version, bad) -> None:
    """A state-feature dataset says so in "phi" and "next" both, from format version 3 on,
    with ``n_state_features`` m and ``n_features = n_actions m``."""
    state = (header.get("phi") == STATE, header["next"] == STATE)
    if state[0] != state[1]:
        raise bad("phi" if state[1] else "next", f"must be {STATE!r} too: 'phi' is "
                  f"{header.get('phi', 'stored')!r} and 'next' is {header['next']!r}, but state "
                  "features serve as both")
    if not state[0]:
        return
    if version < 3:
        raise bad("format_version", f"is {version}, but {STATE!r} datasets have format "
                  "version 3")
    m = header.get("n_state_features")
    if isinstance(m, bool) or not isinstance(m, int) or m < 1:
        raise bad("n_state_features", f"must be an integer >= 1, got {m!r}")
    if header["n_features"] != header["n_actions"] * m:
        raise bad("n_features", f"is {header['n_features']}, but n_actions x n_state_features "
                  f"= {header['n_actions']} x {m} = {header['n_actions'] * m}")


def _check_choice(header, key, choices, bad, default=None):
    value = header.get(key, default)
    if value not in choices or not isinstance(value, str):
        raise bad(key, f"must be one of {list(choices)}, got {value!r}")


def _check_files(path: Path, header: dict, bad) -> None:
    """``files`` maps known fields to file names inside the directory, with every field the
    dataset's forms need; ``shapes`` gives each streamed field's shape, as (H, K, ...) says."""
    files, shapes = header["files"], header["shapes"]
    if not isinstance(files, dict):
        raise bad("files", f"must be an object (field -> file name), got {files!r}")
    if not isinstance(shapes, dict):
        raise bad("shapes", f"must be an object (field -> shape), got {shapes!r}")
    phi_form, next_form = header.get("phi", "stored"), header["next"]
    needed = PHI_FIELDS[phi_form] + ("rewards",) + NEXT_FIELDS[next_form]
    known = set(needed) | set(OPTIONAL_FIELDS)
    for name, fname in files.items():
        if name not in known:
            raise bad(f"files.{name}", f"is not a field of a dataset with 'phi': "
                      f"{phi_form!r} and 'next': {next_form!r}")
        if not isinstance(fname, str) or not fname or fname in (".", "..") or \
                os.path.basename(fname) != fname or "\\" in fname or os.path.isabs(fname):
            raise bad(f"files.{name}", f"must be the name of a file inside {path}, got "
                      f"{fname!r}: r2pvi reads no file outside a dataset directory")
    for name in needed:
        if name not in files:
            raise bad(f"files.{name}", f"is missing: a dataset with 'phi': {phi_form!r} and "
                      f"'next': {next_form!r} needs it")
    H, K = header["horizon"], header["n_trajectories"]
    d, A = header["n_features"], header["n_actions"]
    expected = {"phi": (H, K, d), "rewards": (H, K), "next_phi": (H, K, A, d),
                "psi": (H + 1, K, header.get("n_state_features")),
                "next_values": (H, K, A), "next_index": (H, K), "actions": (H, K),
                "next_action": (H, K), "next_rest": (H, K, A - 1, d),
                "next_side_offsets": (H + 1,)}
    for name in files:
        if name in WHOLE_FIELDS:
            continue
        shape = shapes.get(name)
        if not isinstance(shape, list) or not all(
                isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
            raise bad(f"shapes.{name}", f"must be a list of sizes >= 0, got {shape!r}")
        want = expected.get(name)
        if name in ("observations", "next_observations"):
            ok = tuple(shape[:2]) == (H, K)
            want_text = f"({H}, {K}, ...)"
        elif name == "next_side":
            ok = len(shape) == 2 and shape[1] == d
            want_text = f"(n_side, {d})"
        else:
            ok = tuple(shape) == want
            want_text = str(want)
        if not ok:
            raise bad(f"shapes.{name}", f"is {shape}, but horizon, n_trajectories, "
                      f"n_features and n_actions say {want_text}")


def stored_field(path: Path, mf: dict, name: str, kinds: str = "", dtype=None) -> FileField:
    """The streamed field ``name`` of the dataset directory ``path``: its file's header must
    agree with the manifest's shape, hold numbers of a kind in ``kinds`` ("f", "iu", ...) or
    exactly ``dtype`` when given."""
    f = FileField(path / mf["files"][name], name)
    if list(f.shape) != list(mf["shapes"][name]):
        raise file_error(f.path, name, f"has shape {f.shape}, the manifest says "
                         f"{mf['shapes'][name]}; the dataset is damaged")
    check_dtype(f.path, name, f.dtype, kinds, dtype)
    return f


def check_dtype(path, name, dtype, kinds="", exact=None) -> None:
    """``dtype`` (of the file ``path`` of the field ``name``) is ``exact`` or of a kind in
    ``kinds``, else a ``ValueError`` naming both."""
    if exact is not None and dtype != np.dtype(exact):
        raise file_error(path, name, f"holds {dtype} numbers, the dataset stores "
                         f"{np.dtype(exact)}; the dataset is damaged")
    if kinds and dtype.kind not in kinds:
        what = {"f": "floating-point", "iu": "integer", "i": "signed integer"}.get(kinds, kinds)
        raise file_error(path, name, f"must hold {what} numbers, got {dtype}; the dataset is "
                         "damaged")


#: Fields whose first axis is the step (their errors name it).
STEP_MAJOR = ("gram", "phi_sums", "rewards", "phi", "next_phi", "next_index", "next_values")


def whole_field(path: Path, mf: dict, name: str, shape=None, kinds="f", dtype=None,
                finite=True, what: str = "") -> np.ndarray:
    """The field ``name`` read whole and checked: ``shape`` (a tuple, None for any) of
    ``what`` it holds, its dtype (see :func:`check_dtype`), finiteness (``finite="no-inf"``
    lets NaN through)."""
    file = path / mf["files"][name]
    arr = load_npy(file, name)
    if shape is not None and arr.shape != tuple(shape):
        raise file_error(file, name, f"must hold {what or 'an array'} of shape {tuple(shape)}, "
                         f"got {arr.shape}; the dataset is damaged")
    check_dtype(file, name, arr.dtype, kinds, dtype)
    if finite and arr.dtype.kind == "f":
        bad = np.isinf(arr) if finite == "no-inf" else ~np.isfinite(arr)
        if bad.any():
            first = [int(i) for i in np.argwhere(bad)[0]]
            step = f", step {first[0]}" if name in STEP_MAJOR else ""
            raise file_error(file, name, f"holds {int(bad.sum())} non-finite entries (the "
                             f"first, {float(arr[tuple(first)])!r}, at index {first}{step}); "
                             "the dataset is damaged: write the dataset again from its source")
    return arr


def check_stored_sums(path: Path, mf: dict, grams, sums, n_rows: int) -> None:
    """The stored Gram matrices ``Phi_h^T Phi_h (H, d, d)`` and column sums ``Phi_h^T 1
    (H, d)`` are what they claim to be, as far as they tell without the data: symmetric,
    with a diagonal >= 0 and entries within Cauchy-Schwarz's ``|G_ij| <= sqrt(G_ii G_jj)``,
    positive semi-definite (for ``d <= PSD_CHECK_MAX_D``), sums with
    ``(Phi^T 1)_j^2 <= K G_jj``, and >= 0 for non-negative features."""
    nonneg = mf.get("nonnegative_phi") is True
    fix = (" delete the file and its entry in manifest.json to have fits form them from the "
           "data")
    if grams is not None:
        file = path / mf["files"]["gram"]
        diag = np.diagonal(grams, axis1=1, axis2=2)
        root = np.sqrt(np.maximum(diag, 0.0))
        bound = root[:, :, None] * root[:, None, :]
        tol = 1e-9 * (bound + diag.max(initial=0.0) * 1e-6) + 1e-300
        problems = (
            ("a negative diagonal entry", (diag < 0).any(axis=1)),
            ("an asymmetry", (np.abs(grams - grams.transpose(0, 2, 1)) > tol).any(axis=(1, 2))),
            ("an entry beyond sqrt(G_ii G_jj)", (np.abs(grams) > bound + tol).any(axis=(1, 2))),
            ("a negative entry (the features are non-negative)",
             (grams < 0).any(axis=(1, 2)) if nonneg else np.zeros(len(grams), bool)),
        )
        for what, steps in problems:
            if steps.any():
                raise file_error(file, "gram", f"is not a Gram matrix Phi_h^T Phi_h at step "
                                 f"h = {int(np.argmax(steps))} ({what}): the stored Gram "
                                 f"matrices are damaged;{fix}")
        if grams.shape[-1] <= PSD_CHECK_MAX_D:
            shift = 1e-9 * np.maximum(diag.max(axis=1), 1e-300)
            for h, (g, s) in enumerate(zip(grams, shift, strict=True)):
                try:
                    np.linalg.cholesky(g + s * np.eye(g.shape[0]))
                except np.linalg.LinAlgError:
                    raise file_error(file, "gram", f"is not positive semi-definite at step "
                                     f"h = {h}: the stored Gram matrices are damaged;{fix}") \
                        from None
    if sums is not None:
        file = path / mf["files"]["phi_sums"]
        if nonneg and (sums < 0).any():
            raise file_error(file, "phi_sums", "has negative column sums of non-negative "
                             f"features: the stored sums are damaged;{fix}")
        if grams is not None:
            diag = np.diagonal(grams, axis1=1, axis2=2)
            if (sums ** 2 > n_rows * diag * (1 + 1e-9) + 1e-300).any():
                raise file_error(file, "phi_sums", "disagrees with gram.npy ((Phi^T 1)_j^2 > "
                                 f"K G_jj): the stored sums are damaged;{fix}")
