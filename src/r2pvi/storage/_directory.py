"""Opening and writing a dataset directory of the on-disk format (see :mod:`r2pvi.storage`)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from .._io import _held_kind
from ._behaviour import BEHAVIOUR_VERSION, BehaviourNext, RowFile, _next_form, _write_behaviour
from ._checks import check_float32_range
from ._fields import Field, FileField, MappedField, widen_range
from ._format import (
    FORMAT_VERSION,
    GRAM_FILE,
    KIND,
    SUMS_FILE,
    _add_gram,
    _finish,
    _manifest,
    _temp_dir,
    _write_npy_header,
    check_target,
    clean_stale,
    manifest_range,
)
from ._next import MapNext, NextStates, StoredNext, TableNext
from ._source import StepSource


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
    mf = _manifest(path)
    files = mf["files"]

    def field(name):
        f = FileField(path / files[name])
        if list(f.shape) != list(mf["shapes"][name]):
            raise ValueError(f"{path / files[name]} has shape {f.shape}, the manifest says "
                             f"{mf['shapes'][name]}")
        return f

    needs_map = mf.get("phi", "stored") == "map" or mf["next"] == "map"
    if needs_map and not callable(feature_map):
        raise ValueError(
            f"{path} stores observations, not features: pass the feature_map it was built "
            "with, OfflineDataset.open(path, feature_map=f) with f(observations, actions) -> "
            "(n, d)")
    d = int(mf["n_features"])
    if mf.get("phi", "stored") == "map":
        phi: Field = MappedField(field("observations"), field("actions"), feature_map, d)
    else:
        phi = field("phi")
    rewards = field("rewards")
    if mf["next"] == "map":
        kv = field("next_values") if "next_values" in files else None
        nxt: NextStates = MapNext(field("next_observations"), feature_map,
                                  int(mf["n_actions"]), d, kv)
    elif mf["next"] == "stored":
        nxt = StoredNext(field("next_phi"),
                                     field("next_values") if "next_values" in files else None,
                                     mf.get("nonnegative_next_phi"))
    elif mf["next"] == "behaviour":
        nxt = _open_behaviour(path, mf, field, phi)
    elif mf["next"] == "table":
        table = np.load(path / files["next_table"], allow_pickle=False)
        kt = (np.load(path / files["next_table_values"], allow_pickle=False)
              if "next_table_values" in files else None)
        nxt = TableNext(field("next_index"), table, kt)
    else:
        raise ValueError(f"{path}: unknown next-state form {mf['next']!r}")
    extras = {}
    for name in mf.get("extras", []):
        extras[name] = np.load(path / f"extra_{name}.npy", mmap_mode="r", allow_pickle=False)
    grams = None
    if "gram" in files:
        grams = np.load(path / files["gram"], allow_pickle=False)
        H, d_ = int(mf["horizon"]), int(mf["n_features"])
        if grams.shape != (H, d_, d_) or grams.dtype != np.float64:
            raise ValueError(f"{path / files['gram']} must hold (H, d, d) = {(H, d_, d_)} "
                             f"float64 Gram matrices, got {grams.shape} {grams.dtype}")
    sums = None
    if "phi_sums" in files:  # optional (datasets written before it have none)
        sums = np.load(path / files["phi_sums"], allow_pickle=False)
        H, d_ = int(mf["horizon"]), int(mf["n_features"])
        if sums.shape != (H, d_) or sums.dtype != np.float64:
            raise ValueError(f"{path / files['phi_sums']} must hold (H, d) = {(H, d_)} "
                             f"float64 column sums, got {sums.shape} {sums.dtype}")
    return StepSource(phi, rewards, nxt, extras, mf.get("nonnegative_phi"), grams=grams,
                      sums=sums, reward_range=manifest_range(mf, "reward_range"),
                      reward_noise=_manifest_noise(path, mf),
                      row_sums=manifest_range(mf, "phi_row_sums"))


def _manifest_noise(path: Path, mf: dict) -> float:
    """The rewards' noise level (``OfflineDataset.reward_noise``; 0 when not recorded)."""
    noise = mf.get("reward_noise", 0.0)
    if (isinstance(noise, bool) or not isinstance(noise, int | float) or not np.isfinite(noise)
            or noise < 0):
        raise ValueError(f"{path}: the manifest's reward_noise must be a number >= 0, got "
                         f"{noise!r}")
    return float(noise)


def _open_behaviour(path: Path, mf: dict, field, phi: Field) -> BehaviourNext:
    """The behaviour form's fields, checked against the manifest (each error names the
    field)."""
    files = mf["files"]
    spec = mf.get("next_behaviour")
    if not isinstance(spec, dict) or not isinstance(spec.get("version"), int):
        raise ValueError(f"{path}: the manifest's 'next_behaviour' entry (a dict with a "
                         "'version') is missing or malformed")
    if spec["version"] > BEHAVIOUR_VERSION:
        raise ValueError(f"{path}: next_behaviour version {spec['version']}; this r2pvi reads "
                         f"versions <= {BEHAVIOUR_VERSION}: upgrade r2pvi")
    for name in ("next_action", "next_rest", "next_side", "next_side_offsets"):
        if name not in files or name not in mf.get("shapes", {}):
            raise ValueError(f"{path}: the manifest lists no {name!r} field, which the "
                             "behaviour next-state form needs")
        if not (path / files[name]).is_file():
            raise ValueError(f"{path}: the {name!r} field's file {files[name]} is missing")
    if not isinstance(phi, FileField):
        raise ValueError(f"{path}: the behaviour next-state form needs stored features "
                         "('phi': 'stored')")
    H, K, d = phi.shape
    A = int(mf["n_actions"])
    store = phi.dtype
    action, rest = field("next_action"), field("next_rest")
    if action.dtype.kind != "i":
        raise ValueError(f"{path}: next_action must hold signed integers, got {action.dtype}")
    if action.shape != (H, K):
        raise ValueError(f"{path}: next_action has shape {action.shape}, expected {(H, K)}")
    if rest.shape != (H, K, A - 1, d) or rest.dtype != store:
        raise ValueError(f"{path}: next_rest must be {(H, K, A - 1, d)} {store}, got "
                         f"{rest.shape} {rest.dtype}")
    side = RowFile(path / files["next_side"])
    if list(side.shape) != list(mf["shapes"]["next_side"]) or side.shape[1:] != (d,) or \
            side.dtype != store:
        raise ValueError(f"{path}: next_side must be (n_side, d) {store} as the manifest says "
                         f"{mf['shapes']['next_side']}, got {side.shape} {side.dtype}")
    offsets = np.load(path / files["next_side_offsets"], allow_pickle=False)
    if (offsets.shape != (H + 1,) or offsets.dtype.kind not in "iu" or offsets[0] != 0
            or (np.diff(offsets) < 0).any() or (np.diff(offsets) > K).any()
            or offsets[-1] != side.shape[0] or offsets[-1] - offsets[-2] != K
            or spec.get("n_side") != side.shape[0]):
        raise ValueError(
            f"{path}: next_side_offsets must be (H+1,) = ({H + 1},) non-decreasing integers "
            f"from 0 to the side table's {side.shape[0]} rows (at most K per step, K at the "
            "last step, n_side in the manifest): the dataset is corrupt")
    kv = field("next_values") if "next_values" in files else None
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
        if next_form == "behaviour" and (isinstance(source.phi, MappedField) or isinstance(
                source.next, MapNext | TableNext)):
            raise ValueError(
                "next_form='behaviour' applies to stored next-state features; this dataset "
                "stores observations or next-state indices, which hold no next-state features "
                "to spare: save it with next_form='full'")
        if isinstance(source.phi, MappedField):  # store what it is computed from
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
        if isinstance(nxt, MapNext):
            kind = "map"
            put("next_observations", nxt.observations, nxt.observations.dtype)
            if nxt.has_known_values:
                put("next_values", _Computed((H, K, A), np.float64,
                                             lambda h, s, e: nxt.known(h, s, e)), np.float64)
        elif isinstance(nxt, TableNext):
            kind = "table"
            put("next_index", nxt.index, np.int64)
            files["next_table"] = "next_table.npy"
            np.save(tmp / files["next_table"], np.asarray(nxt.table), allow_pickle=False)
            if nxt.known_table is not None:
                files["next_table_values"] = "next_table_values.npy"
                np.save(tmp / files["next_table_values"], nxt.known_table, allow_pickle=False)
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
            "kind": KIND, "format_version": FORMAT_VERSION, "layout": "step-major",
            "n_trajectories": K, "horizon": H, "n_features": d, "n_actions": A,
            "dtype": store.name, "next": kind, "files": files, "shapes": shapes,
            "extras": extras, **meta,
        }
        return _finish(tmp, path, manifest, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
