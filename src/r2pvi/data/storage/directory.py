"""Opening and writing a dataset directory of the on-disk format (see :mod:`r2pvi.storage`)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ..._io import _held_kind, file_error
from ._finite import file_origin
from .behaviour import BEHAVIOUR_VERSION, BehaviourNext, RowFile, _next_form, _write_behaviour
from .checks import check_float32_range, check_map_actions
from .crossed import CrossedNext
from .fields import Field, widen_range
from .files import FileField
from .format import (
    BASE_FORMAT_VERSION,
    GRAM_FILE,
    KIND,
    MANIFEST,
    STATE_FORMAT_VERSION,
    SUMS_FILE,
    _add_gram,
    _finish,
    _temp_dir,
    check_target,
    clean_stale,
    manifest_range,
)
from .manifest import (
    check_dtype,
    check_stored_sums,
    read_manifest,
    stored_field,
    whole_field,
)
from .next_states import NextStates, StoredNext, TableNext
from .npy import _write_npy_header, load_npy
from .observations import MapNext, MappedField
from .source import StepSource
from .state_files import STATE, is_state_layout, open_state_features, write_state_features


def open_directory(path, feature_map=None) -> StepSource:
    """A :class:`StepSource` over a dataset directory; nothing is read but the headers.

    A dataset stored as observations (``"phi": "map"`` or ``"next": "map"`` in the
    manifest) needs the ``feature_map`` it was built with."""
    path = Path(os.fspath(path))
    clean_stale(path)
    if not path.exists():
        hint = ("; a .npz dataset file is read into memory with OfflineDataset.load(path)"
                if path.suffix == ".npz" else "")
        raise FileNotFoundError(f"no such dataset directory: {path}{hint}")
    if not path.is_dir():
        held = _held_kind(path)
        how = {"OfflineDataset": "a dataset .npz file (the single-file format): load it into "
                                 "memory with OfflineDataset.load(path)",
               "estimator": "an estimator file: load it with r2pvi.load(path)",
               "feature_map": "a feature map file: load it with "
                              "r2pvi.features.load_feature_map(path)"}.get(
            held, "not a dataset directory")
        raise ValueError(f"{path} is a file, {how}; OfflineDataset.open opens the dataset "
                         "directories written by save(dir) or DatasetWriter")
    mf = read_manifest(path)
    files = mf["files"]
    store = mf.get("dtype")

    def field(name, kinds="", dtype=None):
        return stored_field(path, mf, name, kinds, dtype)

    def features(name):  # stored features: the manifest's dtype (float32 or float64)
        f = field(name, "f", store)
        if f.dtype not in (np.float32, np.float64):
            check_dtype(f.path, name, f.dtype, exact=np.float64)
        return f

    needs_map = mf.get("phi", "stored") == "map" or mf["next"] == "map"
    if needs_map and not callable(feature_map):
        raise ValueError(
            f"{path} stores observations, not features: pass the feature_map it was built "
            "with, OfflineDataset.open(path, feature_map=f) with f(observations, actions) -> "
            "(n, d)")
    H, K, d, A = (mf[k] for k in ("horizon", "n_trajectories", "n_features", "n_actions"))
    if needs_map:
        check_map_actions(feature_map, A, f"the manifest of {path} says")
    rewards = field("rewards", dtype=np.float64)
    kv = field("next_values", dtype=np.float64) if "next_values" in files else None
    if mf["next"] == STATE:  # psi and actions memory-mapped, every number checked
        phi: Field = open_state_features(path, mf, field, kv)
    elif mf.get("phi", "stored") == "map":
        phi = MappedField(field("observations"), field("actions", "iu"), feature_map, d)
        _probe_map(path, lambda: phi.read(0, 0, 1))
    else:
        phi = features("phi")
    if mf["next"] == STATE:  # the next observations' rows of the same psi
        nxt: NextStates = CrossedNext(phi.psi, A, kv, mf.get("nonnegative_next_phi"))
    elif mf["next"] == "map":
        nxt = MapNext(field("next_observations"), feature_map, A, d, kv)
        _probe_map(path, lambda: nxt.features(0, 0, 1))
    elif mf["next"] == "stored":
        nxt = StoredNext(features("next_phi"), kv, mf.get("nonnegative_next_phi"))
    elif mf["next"] == "behaviour":
        nxt = _open_behaviour(path, mf, field, features, phi, kv)
    else:  # "table" (read_manifest knows no other form)
        table = whole_field(path, mf, "next_table", dtype=np.float64)
        if table.ndim not in (3, 4) or table.shape[-2:] != (A, d) or (
                table.ndim == 4 and table.shape[0] != H):
            raise file_error(path / files["next_table"], "next_table",
                             f"must have shape (S, A, d) or (H, S, A, d) with (H, A, d) = "
                             f"{(H, A, d)} (the manifest's horizon, n_actions, n_features), "
                             f"got {table.shape}; the dataset is damaged")
        kt = (whole_field(path, mf, "next_table_values", (table.shape[-3], A), dtype=np.float64,
                          finite="no-inf", what="(S, A) known values")
              if "next_table_values" in files else None)
        nxt = TableNext(field("next_index", "iu"), table, kt, {
            n: file_origin(path / files[n]) for n in ("next_table", "next_table_values")
            if n in files})
    extras = {}
    for name in mf.get("extras", []):
        file = path / f"extra_{name}.npy"
        extras[name] = load_npy(file, f"extras.{name}", mmap=True)
        if extras[name].shape[:2] != (K, H):
            raise file_error(file, f"extras.{name}", f"must start with (K, H) = {(K, H)}, "
                             f"got shape {extras[name].shape}; the dataset is damaged")
    grams = (whole_field(path, mf, "gram", (H, d, d), dtype=np.float64,
                         what="(H, d, d) Gram matrices") if "gram" in files else None)
    sums = (whole_field(path, mf, "phi_sums", (H, d), dtype=np.float64,
                        what="(H, d) column sums")
            if "phi_sums" in files else None)  # optional (datasets written before it have none)
    check_stored_sums(path, mf, grams, sums, K)
    return StepSource(phi, rewards, nxt, extras, mf.get("nonnegative_phi"), grams=grams,
                      sums=sums, reward_range=manifest_range(mf, "reward_range"),
                      reward_noise=_manifest_noise(path, mf),
                      row_sums=manifest_range(mf, "phi_row_sums"),
                      range_recorded=True, stationary=_manifest_flag(path, mf, "stationary"),
                      reward_offset=_manifest_offset(path, mf),
                      checked=("phi", "next") if mf["next"] == STATE else (),
                      stored_files={n: path / files[n] for n in ("gram", "phi_sums")
                                    if n in files})


def _probe_map(path: Path, read) -> None:
    """The feature map gives the manifest's ``n_features`` per row (checked on one row)."""
    try:
        read()
    except ValueError as exc:
        if "feature_map returned shape" not in str(exc):
            raise
        raise file_error(path / MANIFEST, "n_features", f"disagrees with the feature map: {exc}; "
                         "pass the feature map the dataset was built with") from None


def _manifest_flag(path: Path, mf: dict, name: str) -> bool:
    """A yes/no fact of the manifest (False when not recorded)."""
    value = mf.get(name, False)
    if not isinstance(value, bool):
        raise ValueError(f"{path}: the manifest's {name} must be true or false, got {value!r}; "
                         "the dataset is damaged")
    return value


def _manifest_offset(path: Path, mf: dict) -> float:
    """The reward shift of episodes (``reward_offset``; 0 when not recorded)."""
    c = mf.get("reward_offset", 0.0)
    if isinstance(c, bool) or not isinstance(c, int | float) or not np.isfinite(c) or c < 0:
        raise ValueError(f"{path}: the manifest's reward_offset must be a number >= 0, got "
                         f"{c!r}; the dataset is damaged")
    return float(c)


def _manifest_noise(path: Path, mf: dict) -> float:
    """The rewards' noise level (``OfflineDataset.reward_noise``; 0 when not recorded)."""
    noise = mf.get("reward_noise", 0.0)
    if (isinstance(noise, bool) or not isinstance(noise, int | float) or not np.isfinite(noise)
            or noise < 0):
        raise ValueError(f"{path}: the manifest's reward_noise must be a number >= 0, got "
                         f"{noise!r}")
    return float(noise)


def _open_behaviour(path: Path, mf: dict, field, features, phi: Field, kv) -> BehaviourNext:
    """The behaviour form's fields, checked against the manifest (each error names the
    field)."""
    files = mf["files"]
    spec = mf.get("next_behaviour")
    where = path / MANIFEST
    if not isinstance(spec, dict) or isinstance(spec.get("version"), bool) or not isinstance(
            spec.get("version"), int):
        raise file_error(where, "next_behaviour", "(an object with a 'version') is missing or "
                         "malformed; the manifest is damaged")
    if spec["version"] > BEHAVIOUR_VERSION:
        raise ValueError(f"{path}: next_behaviour version {spec['version']}; this r2pvi reads "
                         f"versions <= {BEHAVIOUR_VERSION}: upgrade r2pvi")
    if not isinstance(phi, FileField):
        raise file_error(where, "phi", "must be 'stored': the behaviour next-state form needs "
                         "stored features")
    K = phi.shape[1]
    action, rest = field("next_action", "i"), features("next_rest")
    side = RowFile(path / files["next_side"], "next_side")
    if list(side.shape) != list(mf["shapes"]["next_side"]):
        raise file_error(side.path, "next_side", f"has shape {side.shape}, the manifest says "
                         f"{mf['shapes']['next_side']}; the dataset is damaged")
    check_dtype(side.path, "next_side", side.dtype, exact=rest.dtype)
    offsets = whole_field(path, mf, "next_side_offsets", kinds="iu")
    if (offsets[0] != 0 or (np.diff(offsets) < 0).any() or (np.diff(offsets) > K).any()
            or offsets[-1] != side.shape[0] or offsets[-1] - offsets[-2] != K
            or spec.get("n_side") != side.shape[0]):
        raise file_error(
            path / files["next_side_offsets"], "next_side_offsets",
            f"must be non-decreasing integers from 0 to the side table's {side.shape[0]} rows "
            "(at most K per step, K at the last step, n_side in the manifest): the dataset is "
            "damaged")
    return BehaviourNext(action, rest, phi, side, offsets, kv, mf.get("nonnegative_next_phi"))


def _stream_field(out_path: Path, field: Field, dtype, chunk: int, transform=None,
                  name: str = ""):
    """Write ``field`` step by step into a .npy file (bounded memory); finite values beyond
    float32's range refuse a float32 ``dtype`` (they would become inf)."""
    with open(out_path, "wb") as fh:
        _write_npy_header(fh, field.shape, dtype)
        for h in range(field.shape[0]):
            for s, e, rows in field.chunks(h, chunk):
                if transform is not None:
                    rows = transform(h, s, e, rows)
                with np.errstate(over="ignore"):
                    out = np.ascontiguousarray(rows, dtype=dtype)
                check_float32_range(rows, out, name or out_path.stem)
                fh.write(out.tobytes())


class _Computed(Field):
    """A field computed by a function of (h, start, stop): next_phi of a feature map."""

    def __init__(self, shape, dtype, fn):
        self.shape, self.dtype, self.fn = tuple(shape), np.dtype(dtype), fn

    def read(self, h, start=0, stop=None):
        return self.fn(h, start, self.shape[1] if stop is None else stop)


def write_directory(source: StepSource, path, *, dtype=None, overwrite=False,
                    next_form="full") -> Path:
    """Write ``source`` in the on-disk format (streamed step by step; atomic rename).

    ``next_form="behaviour"`` stores stored next-state features without the rows that equal
    the next step's taken-action features (:class:`BehaviourNext`)."""
    path = Path(os.fspath(path))
    next_form = _next_form(next_form)
    check_target(path, overwrite)  # before any work (checked again at the rename)
    store = np.dtype(dtype) if dtype is not None else np.dtype(
        np.float32 if source.phi.dtype == np.float32 else np.float64)
    if store not in (np.float32, np.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    tmp = _temp_dir(path)
    try:
        files, shapes = {}, {}

        def put(name, field, dt, transform=None):
            files[name] = name + ".npy"
            shapes[name] = list(field.shape)
            _stream_field(tmp / files[name], field, dt, source.chunk, transform, name)

        phi_kind = "stored"
        row_sums = [np.inf, -np.inf]  # of the stored phi rows' sums (gram_of_stored)
        state = is_state_layout(source)
        if next_form == "behaviour" and (state or isinstance(source.phi, MappedField)
                                         or isinstance(source.next, MapNext | TableNext)):
            raise ValueError(
                "next_form='behaviour' applies to stored next-state features; this dataset "
                "stores state features once per observation, observations or next-state "
                "indices, which hold no next-state features to spare: save it with "
                "next_form='full'")
        if state:  # psi and actions, written below
            phi_kind = STATE
        elif isinstance(source.phi, MappedField):  # store what it is computed from
            phi_kind = "map"
            put("observations", source.phi.observations, source.phi.observations.dtype)
            put("actions", source.phi.actions, source.phi.actions.dtype)
        else:  # with the Gram matrices of the stored (rounded) features, as they stream by
            grams = np.zeros((source.horizon, source.n_features, source.n_features))
            sums = np.zeros((source.horizon, source.n_features))

            def gram_of_stored(h, s, e, rows):
                with np.errstate(over="ignore"):
                    cast = np.asarray(rows, dtype=store)
                check_float32_range(rows, cast, "phi")
                _add_gram(grams[h], cast, sums[h], row_sums)
                return cast

            put("phi", source.phi, store, gram_of_stored)
            files["gram"] = GRAM_FILE
            np.save(tmp / GRAM_FILE, grams, allow_pickle=False)
            files["phi_sums"] = SUMS_FILE
            np.save(tmp / SUMS_FILE, sums, allow_pickle=False)
        bounds = [np.inf, -np.inf]

        def rewards_range(h, s, e, rows):  # the rewards' range, as they stream by
            bounds[:] = widen_range((bounds[0], bounds[1]), rows)
            return rows

        put("rewards", source.rewards, np.float64, rewards_range)
        nxt = source.next
        H, K, d = source.phi.shape
        A = nxt.n_actions
        meta = {"nonnegative_phi": source.nonnegative_phi, "phi": phi_kind,
                "reward_range": [float(bounds[0]), float(bounds[1])]}
        if np.isfinite(row_sums).all():
            meta["phi_row_sums"] = [float(row_sums[0]), float(row_sums[1])]
        if source.reward_noise:
            meta["reward_noise"] = source.reward_noise
        if source.stationary:
            meta["stationary"] = True
        if source.reward_offset:
            meta["reward_offset"] = source.reward_offset
        if state:
            kind = STATE
            write_state_features(source, put, store, meta)
        elif isinstance(nxt, MapNext):
            kind = "map"
            put("next_observations", nxt.observations, nxt.observations.dtype)
            if nxt.has_known_values:
                put("next_values", _Computed((H, K, A), np.float64,
                                             lambda h, s, e: nxt.known(h, s, e)), np.float64)
        elif isinstance(nxt, TableNext):
            kind = "table"
            put("next_index", nxt.index, np.int64)
            files["next_table"] = "next_table.npy"
            np.save(tmp / files["next_table"], np.ascontiguousarray(nxt.table, dtype=np.float64),
                    allow_pickle=False)
            if nxt.known_table is not None:
                files["next_table_values"] = "next_table_values.npy"
                np.save(tmp / files["next_table_values"],
                        np.ascontiguousarray(nxt.known_table, dtype=np.float64),
                        allow_pickle=False)
        else:
            kind = "stored"
            feats = nxt.next_phi if isinstance(nxt, StoredNext) else _Computed(
                (H, K, A, d), store, nxt.features)
            if next_form == "behaviour":
                kind = "behaviour"
                meta["next_behaviour"] = _write_behaviour(tmp, files, shapes, source.phi,
                                                          feats, store, source.chunk)
            else:
                put("next_phi", feats, store,
                    lambda h, s, e, rows: np.nan_to_num(rows, nan=0.0) if h == H - 1 else rows)
            if nxt.has_known_values:
                kv = nxt.next_values if isinstance(nxt, StoredNext) else _Computed(
                    (H, K, A), np.float64,
                    lambda h, s, e: nxt.known(h, s, e))
                put("next_values", kv, np.float64)
            meta["nonnegative_next_phi"] = nxt.nonnegative
        extras = []
        for name, value in source.extras.items():
            value = np.asarray(value)
            if value.dtype.hasobject:
                raise TypeError(f"cannot save {name!r}: object arrays are not supported")
            np.save(tmp / f"extra_{name}.npy", value, allow_pickle=False)
            extras.append(name)
        manifest = {
            "kind": KIND, "layout": "step-major",
            "format_version": STATE_FORMAT_VERSION if state else BASE_FORMAT_VERSION,
            "n_trajectories": K, "horizon": H, "n_features": d, "n_actions": A,
            "dtype": store.name, "next": kind, "files": files, "shapes": shapes,
            "extras": extras, **meta,
        }
        return _finish(tmp, path, manifest, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
