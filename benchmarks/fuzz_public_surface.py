"""Scripted damage to every loader and public constructor, each outcome classified.

Run from a checkout (about 10 s, one core)::

    PYTHONPATH=src python benchmarks/fuzz_public_surface.py [--show CLASS] [--group GROUP]

Cases: saved dataset directories of every next-state form (stored, behaviour, table,
observations + feature map) with each manifest key deleted or of a wrong type, each ``files``
entry pointing elsewhere (outside the directory, an absolute path, a missing file, an
``.npz``), each shape wrong, each ``.npy`` emptied, truncated, garbage, of a wrong dtype or
shape, Fortran-ordered, an object array or an ``.npz``; single-file ``.npz`` datasets, saved
estimators and feature maps with each field deleted, non-finite, of a wrong shape, dtype or
range; saves over a user's directory or file; bad arguments of every public estimator and
dataset constructor. Each outcome is one of

- ``clear``: a ``ValueError``, ``TypeError`` or ``FileExistsError`` (``FileNotFoundError``
  where a path given by the caller does not exist) whose message names the file or the
  argument (and, for a damaged manifest key, the key), never NumPy's ``allow_pickle`` advice;
- ``obscure``: any other exception, or a message naming neither;
- ``silent``: no error where one was due (a damaged file read as if whole, a fit whose
  result differs from the undamaged one's, non-finite weights);
- ``data loss``: a file or directory of the user's changed or deleted;
- ``accepted``: no error and none was due (an optional manifest key deleted, a valid
  argument value), the result checked.

Prints the counts per class and group and lists the cases of the class ``--show`` (default:
obscure, silent and data loss).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import traceback
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import r2pvi
from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, DatasetWriter, OfflineDataset
from r2pvi.sparse import SparseOfflineDataset

K, H, A, D = 16, 3, 2, 4
CLEAR_TYPES = (ValueError, TypeError, FileExistsError)
META = "__r2pvi_meta__"


@dataclass
class Case:
    group: str
    name: str
    run: object  # () -> result; raises on error
    due: bool  # an error is due
    names: list = field(default_factory=list)  # groups of alternatives the message must name
    check: object = None  # (result) -> True when an accepted result is right
    guard: object = None  # () -> True when the user's files are intact (saves)
    extra_types: tuple = ()


def classify(case: Case) -> tuple[str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = case.run()
        except CLEAR_TYPES + case.extra_types as exc:
            msg = f"{type(exc).__name__}: {exc}"
            if case.guard is not None and not case.guard():
                return "data loss", msg
            named = all(any(n in str(exc) for n in alts) for alts in case.names)
            if "allow_pickle" in str(exc) or not named:
                return "obscure", msg
            return "clear", msg
        except Exception as exc:  # noqa: BLE001 - classifying every outcome is the point
            tb = traceback.extract_tb(exc.__traceback__)[-1]
            where = f" [{Path(tb.filename).name}:{tb.lineno}]"
            if case.guard is not None and not case.guard():
                return "data loss", f"{type(exc).__name__}: {exc}"
            return "obscure", f"{type(exc).__name__}: {exc}{where}"
    if case.guard is not None and not case.guard():
        return "data loss", "no error"
    try:
        ok = case.check(result) if case.check is not None else True
    except Exception as exc:  # noqa: BLE001
        return "obscure", f"the result could not be used: {type(exc).__name__}: {exc}"
    if case.due or not ok:
        return "silent", "no error" + ("" if ok else " and a different result")
    return "accepted", "no error"


# ---------------------------------------------------------------- data
def feature_map(obs, act):
    """(n, ...) observations x actions -> (n, D) simplex rows (a softmax of the first two
    numbers of each observation); records its n_actions, as r2pvi's cross_actions maps do."""
    obs = np.real(np.asarray(obs)).astype(float).reshape(len(obs), -1)
    obs = np.concatenate([obs, obs], axis=1)
    act = np.asarray(act)
    z = np.stack([obs[:, 0], obs[:, 1], obs[:, 0] * act, 1.0 - obs[:, 1] * act], axis=1)
    e = np.exp(z - z.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


feature_map.n_actions = A


def datasets(rng):
    """The in-memory datasets of every next-state form."""
    phi = rng.dirichlet(np.ones(D), (K, H))
    rewards = rng.random((K, H))
    nphi = rng.dirichlet(np.ones(D), (K, H, A))
    nv = np.full((K, H, A), np.nan)
    nv[:3, :, 1] = 0.5
    stored = OfflineDataset.from_features(phi, rewards, nphi, nv,
                                          states=rng.random((K, H, 2)))
    # trajectories: phi[k, h+1] is next_phi[k, h, taken] (the behaviour form stores less)
    taken = rng.integers(A, size=(K, H))
    tphi = phi.copy()
    tphi[:, 1:] = nphi[np.arange(K)[:, None], np.arange(H - 1), taken[:, 1:]]
    behaviour = OfflineDataset.from_features(tphi, rewards, nphi)
    S = 5
    table = rng.dirichlet(np.ones(D), (S, A))
    idx = rng.integers(S, size=(K, H))
    known = np.full((S, A), np.nan)
    known[0] = 0.0
    tab = OfflineDataset.from_next_state_table(phi, rewards, idx, table, known)
    obs, nobs = rng.random((K, H, 2)), rng.random((K, H, 2))
    acts = rng.integers(A, size=(K, H))
    mapped = OfflineDataset.from_observations(obs, acts, rewards, nobs, feature_map, A)
    return {"stored": (stored, "full"), "behaviour": (behaviour, "behaviour"),
            "table": (tab, "full"), "map": (mapped, "full")}


def fit(ds):
    return R2PVI("tv", lam=0.5, beta=0.1).fit(ds).weights_


def same(a, b):
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------- damage
def _npy_bytes(arr) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _header_bytes(shape, descr, fortran=False) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": fortran,
                                               "shape": tuple(shape)})
    return buf.getvalue()


def _wrong_type(value):
    if isinstance(value, bool):
        return "yes"
    if isinstance(value, int | float):
        return "7"
    if isinstance(value, str):
        return 5
    if isinstance(value, dict):
        return [1, 2]
    if isinstance(value, list):
        return {"a": 1}
    return "x"


# Manifest keys a dataset opens and fits the same without (deleted: "accepted").
OPTIONAL_KEYS = {"reward_range", "phi_row_sums", "reward_noise", "extras", "layout", "dtype",
                 "nonnegative_phi", "nonnegative_next_phi", "phi"}
# Keys whose wrong-typed value is ignored (recomputed from the data): no error due.
IGNORED_IF_WRONG = {"reward_range", "phi_row_sums"}
OPTIONAL_FILES = {"gram", "phi_sums", "next_values", "next_table_values"}


def directory_cases(root: Path, form: str, template: Path, fmap, base) -> list[Case]:
    mf = json.loads((template / "manifest.json").read_text())
    cases = []
    counter = [0]

    def fresh():
        counter[0] += 1
        p = root / f"{form}-{counter[0]}"
        shutil.copytree(template, p)
        return p

    def opener(p):
        def run():
            return fit(OfflineDataset.open(p, feature_map=fmap))
        return run

    def add(name, damage, due, names, check=None):
        p = fresh()
        damage(p)
        alts = [[str(p)] + [n for n in names[0]]] + [list(g) for g in names[1:]]
        cases.append(Case(f"dir:{form}", name, opener(p), due, alts,
                          check or (lambda w: same(w, base))))

    def write_manifest(new):
        return lambda p: (p / "manifest.json").write_text(json.dumps(new))

    M = ["manifest.json"]
    add("manifest empty", lambda p: (p / "manifest.json").write_text(""), True, [M])
    add("manifest not JSON", lambda p: (p / "manifest.json").write_text("{kind: oops"), True, [M])
    add("manifest truncated", lambda p: (p / "manifest.json").write_text(
        json.dumps(mf)[:40]), True, [M])
    add("manifest binary", lambda p: (p / "manifest.json").write_bytes(b"\xff\xfe\x00garbage"),
        True, [M])
    add("manifest a JSON list", write_manifest([mf]), True, [M])
    add("manifest a JSON string", write_manifest("dataset"), True, [M])
    for key, value in mf.items():
        rest = {k: v for k, v in mf.items() if k != key}
        add(f"manifest key {key!r} deleted", write_manifest(rest), key not in OPTIONAL_KEYS,
            [M, [key]])
        add(f"manifest key {key!r} of a wrong type", write_manifest({**mf, key: _wrong_type(
            value)}), key not in IGNORED_IF_WRONG, [M, [key]])
        if isinstance(value, int) and not isinstance(value, bool):
            for bad in (-1, 0, value + 1, 2.5):
                if bad == value:
                    continue
                add(f"manifest key {key!r} = {bad}", write_manifest({**mf, key: bad}), True,
                    [M, [key]])
    for name, fname in mf["files"].items():
        files = dict(mf["files"])

        def move(target_fn, name=name, fname=fname, files=files):
            def damage(p):
                src = p / fname
                dst = target_fn(p)
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(src, dst)
                rel = os.path.relpath(dst, p) if not str(target_fn).startswith("abs") else dst
                new = {**mf, "files": {**files, name: str(rel)}}
                (p / "manifest.json").write_text(json.dumps(new))
            return damage

        add(f"files.{name} outside the directory (../)",
            move(lambda p, f=fname: p.parent / f"outside-{p.name}" / f), True, [[fname, name]])

        def absolute(p, name=name, fname=fname, files=files):
            dst = p.parent / f"abs-{p.name}-{fname}"
            shutil.copy(p / fname, dst)
            (p / "manifest.json").write_text(json.dumps(
                {**mf, "files": {**files, name: str(dst)}}))

        add(f"files.{name} an absolute path", absolute, True, [[fname, name]])
        add(f"files.{name} a missing file", write_manifest(
            {**mf, "files": {**files, name: "nope.npy"}}), True, [["nope.npy", name]])
        add(f"files.{name} not a string", write_manifest(
            {**mf, "files": {**files, name: 5}}), True, [[name]])

        def to_npz(p, name=name, fname=fname, files=files):
            np.savez(p / "x.npz", a=np.load(p / fname, allow_pickle=False))
            (p / "manifest.json").write_text(json.dumps(
                {**mf, "files": {**files, name: "x.npz"}}))

        add(f"files.{name} an .npz", to_npz, True, [["x.npz"]])
        add(f"files.{name} -> manifest.json", write_manifest(
            {**mf, "files": {**files, name: "manifest.json"}}), True, [["manifest.json"]])
        if name not in OPTIONAL_FILES:
            add(f"files.{name} deleted", write_manifest(
                {**mf, "files": {k: v for k, v in files.items() if k != name}}), True, [[name]])
        elif name in ("gram", "phi_sums"):  # cached sums: fits form them from the data
            def drop(p, name=name, fname=fname, files=files):
                (p / fname).unlink()
                (p / "manifest.json").write_text(json.dumps(
                    {**mf, "files": {k: v for k, v in files.items() if k != name}}))
            add(f"files.{name} and its file deleted", drop, False, [[name]])
    for name, shape in mf.get("shapes", {}).items():
        shapes = dict(mf["shapes"])
        add(f"shapes.{name} deleted", write_manifest(
            {**mf, "shapes": {k: v for k, v in shapes.items() if k != name}}), True, [[name]])
        add(f"shapes.{name} wrong", write_manifest(
            {**mf, "shapes": {**shapes, name: [s + 1 for s in shape]}}), True, [[name]])
        add(f"shapes.{name} not a list", write_manifest(
            {**mf, "shapes": {**shapes, name: "big"}}), True, [[name]])
    for bad in ("table", "stored", "map", "behaviour", "bogus"):
        if bad != mf["next"]:
            add(f"next = {bad!r}", write_manifest({**mf, "next": bad}), True, [["next"]])
    # the .npy files
    # Data edits no check can tell from real data: another numeric dtype for fields whose
    # dtype the format leaves free (observations, extras), the Fortran flag of fields that
    # may be stored in either order (read whole): "accepted" whatever the fit gives.
    free_dtype = {"observations.npy", "next_observations.npy"}
    any_order = {"gram.npy", "phi_sums.npy", "next_table.npy", "next_table_values.npy"}
    for fname in sorted(f.name for f in template.glob("*.npy")):
        arr = np.load(template / fname, allow_pickle=False)
        raw = (template / fname).read_bytes()
        F = [[fname]]
        extra = fname.startswith("extra_")

        def add_edit(name, damage, due, names, fname=fname, extra=extra):
            free = (extra or fname in free_dtype) and ("dtype" in name or "float" in name)
            order = (extra or fname in any_order) and "Fortran" in name
            if free or order:
                add(name, damage, False, names, check=lambda w: True)
            else:
                add(name, damage, due, names)

        def put(data, fname=fname):
            return lambda p: (p / fname).write_bytes(data)

        add_edit(f"{fname} empty", put(b""), True, F)
        add_edit(f"{fname} garbage", put(bytes(np.random.default_rng(1).integers(
            0, 256, len(raw), dtype=np.uint8))), True, F)
        add_edit(f"{fname} text", put(b"not an array at all\n" * 4), True, F)
        add_edit(f"{fname} truncated data", put(raw[:-8]), True, F)
        add_edit(f"{fname} truncated header", put(raw[:30]), True, F)
        add_edit(f"{fname} an .npz", lambda p, fname=fname, arr=arr: np.savez(
            open(p / fname, "wb"), a=arr), True, F)
        other = np.int64 if arr.dtype.kind == "f" else np.float64
        add_edit(f"{fname} dtype {np.dtype(other).name}", put(_npy_bytes(arr.astype(other))),
            True, F)
        if arr.dtype == np.float32:
            add_edit(f"{fname} float64", put(_npy_bytes(arr.astype(np.float64))), True, F)
        if arr.dtype == np.float64:
            add_edit(f"{fname} float32", put(_npy_bytes(arr.astype(np.float32))), True, F)
        add_edit(f"{fname} object dtype", put(_header_bytes(arr.shape, "|O") + b"\x00" * 64), True,
            F)
        add_edit(f"{fname} bytes dtype", put(_npy_bytes(np.zeros(arr.shape, "S8"))), True, F)
        add_edit(f"{fname} complex", put(_npy_bytes(arr.astype(np.complex128))), True, F)
        if arr.ndim >= 2:
            add_edit(f"{fname} Fortran order", put(_header_bytes(
                arr.shape, np.lib.format.dtype_to_descr(arr.dtype), True)
                + np.ascontiguousarray(arr).tobytes()), True, F)
        bigger = np.concatenate([arr, arr[:1]]) if arr.ndim else np.array([arr, arr])
        add_edit(f"{fname} one more row", put(_npy_bytes(bigger)), True, F)
        add_edit(f"{fname} one dimension less", put(_npy_bytes(arr.reshape(-1))), arr.ndim > 1, F)
        if fname in ("gram.npy", "phi_sums.npy"):
            add_edit(f"{fname} negated", put(_npy_bytes(-arr)), True, F)
            add_edit(f"{fname} NaN", put(_npy_bytes(np.where(np.arange(arr.size).reshape(
                arr.shape) == 1, np.nan, arr))), True, F)
        if fname == "gram.npy":
            g = arr.copy()
            g[:, 0, 1] += 10 * np.sqrt(g[:, 0, 0] * g[:, 1, 1]) + 1  # not a Gram matrix
            g[:, 1, 0] = g[:, 0, 1]
            add_edit(f"{fname} not positive semi-definite", put(_npy_bytes(g)), True, F)
    return cases


def npz_dataset_cases(root: Path, ds, base) -> list[Case]:
    src = ds.save(root / "single.npz")
    with np.load(src, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    cases = []

    def add(name, make, due=True, names=("bad.npz",)):
        p = root / f"bad-{len(cases)}.npz"
        make(p)
        cases.append(Case("npz:dataset", name, lambda p=p: fit(OfflineDataset.load(p)), due,
                          [[str(p)], *[[n, n.removeprefix("extra_")] for n in names[1:]]],
                          (lambda w: same(w, base)) if due else None))

    raw = src.read_bytes()
    add("empty", lambda p: p.write_bytes(b""))
    add("truncated", lambda p: p.write_bytes(raw[: len(raw) // 2]))
    add("garbage", lambda p: p.write_bytes(os.urandom(len(raw))))
    add("a .npy", lambda p: p.write_bytes(_npy_bytes(members["phi"])))
    for key, value in members.items():
        rest = {k: v for k, v in members.items() if k != key}
        add(f"member {key} deleted", lambda p, rest=rest: np.savez(p, **rest),
            not key.startswith("extra_"), ("", key))
        if key == META:
            header = json.loads(str(value))
            for hk in header:
                h2 = {k: v for k, v in header.items() if k != hk}
                add(f"header {hk} deleted", lambda p, h2=h2: np.savez(
                    p, **{**members, META: np.array(json.dumps(h2))}), hk != "reward_noise",
                    ("", hk))
            add("header a list", lambda p: np.savez(p, **{**members, META: np.array("[1]")}),
                True, ("", "header"))
            continue
        if key != "next_values" and not key.startswith("extra_"):  # NaN: valid there
            add(f"member {key} NaN", lambda p, key=key, value=value: np.savez(
                p, **{**members, key: np.full(value.shape, np.nan)}), True, ("", key))
        add(f"member {key} wrong shape", lambda p, key=key, value=value: np.savez(
            p, **{**members, key: value.reshape(-1)}), True, ("", key))
        add(f"member {key} strings", lambda p, key=key, value=value: np.savez(
            p, **{**members, key: np.zeros(value.shape, "U3")}), not key.startswith("extra_"),
            ("", key))
    return cases


def _rewrite_npz(src, p, members, header):
    np.savez(p, **{**members, META: np.array(json.dumps(header))})


def model_cases(root: Path, rng) -> list[Case]:
    import scipy.sparse as sp

    ds_small = datasets(rng)["stored"][0]
    phi = [sp.csr_matrix(rng.dirichlet(np.ones(D), K) * (rng.random((K, D)) < 0.6))
           for _ in range(H)]
    nxt = [sp.csr_matrix(rng.dirichlet(np.ones(D), K * A)) for _ in range(H)]
    sparse = SparseOfflineDataset.from_rows(phi, rng.random((K, H)), nxt, A)
    wide_phi = rng.dirichlet(np.ones(40), (8, H))  # d > K: the dual form
    wide = OfflineDataset.from_features(wide_phi, rng.random((8, H)),
                                        rng.dirichlet(np.ones(40), (8, H, A)))
    fitted = {
        "PEVI": (PEVI().fit(ds_small), ds_small),
        "R2PVI-kl": (R2PVI("kl", lam=0.5, penalty="elliptical").fit(ds_small), ds_small),
        "DRPVI": (DRPVI(0.1).fit(ds_small), ds_small),
        "DRVIL": (DRVIL(0.1, penalty="elliptical").fit(ds_small), ds_small),
        "PEVI-sparse": (PEVI().fit(sparse), None),
        "PEVI-dual": (PEVI().fit(wide), wide),
    }
    cases = []
    probe = rng.dirichlet(np.ones(D), (5, A))
    for tag, (est, _) in fitted.items():
        path = est.save(root / f"model-{tag}.npz")
        with np.load(path, allow_pickle=False) as z:
            members = {k: z[k] for k in z.files if k != META}
            header = json.loads(str(z[META]))
        d = est.weights_.shape[1]
        x = probe if d == D else rng.dirichlet(np.ones(d), (5, A))
        ref = est.q_values(x, 0)

        def check(loaded, x=x, ref=ref):
            return np.allclose(loaded.q_values(x, 0), ref, rtol=1e-9, atol=1e-12)

        def add(name, mem, hdr, due, key, tag=tag, path=path, check=check):
            p = root / f"model-{tag}-{len(cases)}.npz"
            _rewrite_npz(path, p, mem, hdr)
            cases.append(Case(f"model:{tag}", name, lambda p=p: r2pvi.load(p), due,
                              [[str(p)], [key]], check))

        for key, value in members.items():
            rest = {k: v for k, v in members.items() if k != key}
            add(f"{key} deleted", rest, header, True, key)
            if value.dtype.kind == "f":
                add(f"{key} NaN", {**members, key: np.where(
                    np.arange(value.size).reshape(value.shape) == 0, np.nan, value)}, header,
                    True, key)
                add(f"{key} inf", {**members, key: np.full(value.shape, np.inf)}, header, True,
                    key)
                if key in ("gram_inv_diag_", "elliptical_c", "param_rho"):
                    add(f"{key} negated", {**members, key: -value}, header, True, key)
            add(f"{key} wrong shape", {**members, key: np.concatenate(
                [value.reshape(-1), value.reshape(-1)[:1]])}, header, True, key)
            add(f"{key} strings", {**members, key: np.zeros(value.shape, "U2")}, header, True,
                key)
        if "elliptical_c" in members:
            c = members["elliptical_c"]
            for label, bad in (("negative", c - np.abs(c).max() - 1.0), ("scaled", 2 * c + 1),
                               ("zero", np.zeros_like(c))):
                add(f"elliptical_c {label}", {**members, "elliptical_c": bad}, header, True,
                    "elliptical_c")
        for hk, hv in header.items():
            if hk in ("kind", "format_version"):
                continue
            add(f"header {hk} deleted", members, {k: v for k, v in header.items()
                                                  if k != hk}, True, hk)
            add(f"header {hk} of a wrong type", members, {**header, hk: _wrong_type(hv)},
                True, hk)
        for pk, pv in header["params"].items():
            for bad in (-1.0, "bogus", None, [1.0, 2.0]):
                if bad == pv or (isinstance(pv, dict)):
                    continue
                hdr = {**header, "params": {**header["params"], pk: bad}}
                add(f"params.{pk} = {bad!r}", members, hdr, None, pk)
        add("n_actions 0", members, {**header, "n_actions": 0}, True, "n_actions")
        add("elliptical_index out of range", members, {
            **header, "elliptical_index": [99] * H}, "elliptical_index" in header,
            "elliptical_index")
    # a parameter value may be valid (-1.0 for v_min, None for reward_weights): an error is due
    # only when the loaded model differs from the saved one
    for c in cases:
        if c.due is None:
            c.due = False
    return cases


def feature_map_cases(root: Path, rng) -> list[Case]:
    from r2pvi.features import (
        NormalizedRBF,
        StateAggregation,
        TileCoding,
        cross_actions,
        load_feature_map,
    )

    X = rng.normal(size=(40, 2))
    cases = []
    for m in (NormalizedRBF(n_centers=3).fit(X),
              TileCoding(n_tilings=2, n_tiles=3).fit(X), StateAggregation(n_bins=3).fit(X)):
        fmap = cross_actions(m, n_actions=A)
        tag = type(m).__name__
        path = fmap.save(root / f"fmap-{tag}.npz")
        ref = fmap(X[:5], np.ones(5, int))
        ref = ref.toarray() if hasattr(ref, "toarray") else ref
        with np.load(path, allow_pickle=False) as z:
            members = {k: z[k] for k in z.files if k != META}
            header = json.loads(str(z[META]))

        def check(loaded, ref=ref):
            out = loaded(X[:5], np.ones(5, int))
            out = out.toarray() if hasattr(out, "toarray") else out
            return np.allclose(out, ref)

        def add(name, mem, hdr, due, key, tag=tag, path=path, check=check):
            p = root / f"fmap-{tag}-{len(cases)}.npz"
            _rewrite_npz(path, p, mem, hdr)
            cases.append(Case(f"feature map:{tag}", name, lambda p=p: load_feature_map(p), due,
                              [[str(p)], [key]], check))

        for key, value in members.items():
            add(f"{key} deleted", {k: v for k, v in members.items() if k != key}, header, True,
                key.split("_", 2)[-1])
            if value.dtype.kind == "f":
                add(f"{key} NaN", {**members, key: np.full(value.shape, np.nan)}, header, True,
                    key.split("_", 2)[-1])
            add(f"{key} strings", {**members, key: np.zeros(value.shape, "U2")}, header, True,
                key.split("_", 2)[-1])
        for hk, hv in header.items():
            if hk in ("kind", "format_version"):
                continue
            add(f"header {hk} deleted", members, {k: v for k, v in header.items() if k != hk},
                hk != "n_actions", hk)
            add(f"header {hk} of a wrong type", members, {**header, hk: _wrong_type(hv)}, True,
                hk)
        spec = header["state_map"]
        for sk, sv in spec.items():
            add(f"state_map.{sk} deleted", members, {**header, "state_map": {
                k: v for k, v in spec.items() if k != sk}}, True, sk)
            add(f"state_map.{sk} of a wrong type", members, {**header, "state_map": {
                **spec, sk: _wrong_type(sv)}}, True, sk)
        add("n_actions 0", members, {**header, "n_actions": 0}, True, "n_actions")
    return cases


def save_cases(root: Path, rng) -> list[Case]:
    ds = datasets(rng)["stored"][0]
    est = PEVI().fit(ds)
    cases = []

    def user_dir(p):
        p.mkdir()
        (p / "thesis.tex").write_text("results")
        return p

    def user_file(p):
        p.write_text("my notes")
        return p

    def dataset_plus(p):
        from r2pvi.storage import write_directory

        write_directory(ds._source, p)  # a directory, whatever the suffix
        (p / "README").write_text("mine")
        return p

    def empty_file(p):
        p.touch()
        return p

    saves = {
        "OfflineDataset.save(dir, overwrite=True)": lambda p: ds.save(p, overwrite=True),
        "OfflineDataset.save(.npz, overwrite=True)": lambda p: ds.save(p, overwrite=True),
        "DatasetWriter(overwrite=True)": lambda p: DatasetWriter(
            p, horizon=H, n_features=D, n_actions=A, overwrite=True),
        "estimator.save": lambda p: est.save(p),
    }
    for what, make in (("a user directory", user_dir), ("a user file", user_file),
                       ("a dataset directory with a user file", dataset_plus),
                       ("an empty file", empty_file)):
        for how, save in saves.items():
            p = root / f"save-{len(cases)}" / ("x.npz" if ".npz" in how or "estimator" in how
                                               else "x")
            p.parent.mkdir()
            make(p)
            snap = _snapshot(p.parent)
            empty_ok = what == "an empty file" and (".npz" in how or "estimator" in how)
            cases.append(Case("save", f"{how} over {what}", lambda s=save, p=p: s(p),
                              not empty_ok, [[str(p), p.name]],
                              guard=lambda p=p, snap=snap, ok=empty_ok: ok or
                              _snapshot(p.parent) == snap,
                              extra_types=(IsADirectoryError,)))
    return cases


def _snapshot(root: Path) -> dict:
    return {str(q.relative_to(root)): q.read_bytes() for q in sorted(root.rglob("*"))
            if q.is_file()}


BAD_VALUES = {"None": None, "'x'": "x", "-1": -1, "0": 0, "nan": float("nan"),
              "inf": float("inf"), "1.79e308": 1.79e308, "1e-320": 1e-320, "True": True,
              "[1, 2]": [1.0, 2.0], "{}": {}, "1j": 1j}


def _finite_weights(est):
    return bool(np.isfinite(est.weights_).all())


def estimator_cases(rng) -> list[Case]:
    ds = datasets(rng)["stored"][0]
    makers = {
        "PEVI": lambda **kw: PEVI(**kw),
        "R2PVI-tv": lambda **kw: R2PVI("tv", **kw),
        "R2PVI-kl": lambda **kw: R2PVI("kl", **kw),
        "R2PVI-chi2": lambda **kw: R2PVI("chi2", **kw),
        "R2PVI-hellinger": lambda **kw: R2PVI("hellinger", **kw),
        "DRPVI": lambda **kw: DRPVI(**{"rho": 0.1, **kw}),
        "DRVIL": lambda **kw: DRVIL(**{"rho": 0.1, **kw}),
    }
    cases = []
    for tag, make in makers.items():
        params = make().get_params()
        for pname in params:
            for label, bad in BAD_VALUES.items():
                def run(make=make, pname=pname, bad=bad):
                    return make(**{pname: bad}).fit(ds)
                cases.append(Case(f"estimator:{tag}", f"{pname}={label}", run, False,
                                  [[pname]], _finite_weights))
    cases.append(Case("estimator:DRVIL", "b_min=1.79e308 (rho=0.2)", lambda: DRVIL(
        0.2, b_min=1.79e308).fit(ds), False, [["b_min"]], _finite_weights))
    return cases


def constructor_cases(rng) -> list[Case]:
    import scipy.sparse as sp

    phi = rng.dirichlet(np.ones(D), (K, H))
    rewards = rng.random((K, H))
    nphi = rng.dirichlet(np.ones(D), (K, H, A))
    states = rng.random((K, H, 2))
    acts = rng.integers(A, size=(K, H))
    base_args = {
        "from_features": (OfflineDataset.from_features,
                          {"phi": phi, "rewards": rewards, "next_phi": nphi}),
        "from_transitions": (OfflineDataset.from_transitions,
                             {"states": states, "actions": acts, "rewards": rewards,
                              "next_states": states, "feature_map": feature_map,
                              "n_actions": A}),
        "from_observations": (OfflineDataset.from_observations,
                              {"states": states, "actions": acts, "rewards": rewards,
                               "next_states": states, "feature_map": feature_map,
                               "n_actions": A}),
        "from_next_state_table": (OfflineDataset.from_next_state_table,
                                  {"phi": phi, "rewards": rewards,
                                   "next_states": rng.integers(3, size=(K, H)),
                                   "table": rng.dirichlet(np.ones(D), (3, A))}),
        "SparseOfflineDataset.from_rows": (
            SparseOfflineDataset.from_rows,
            {"phi": [sp.csr_matrix(phi[:, h]) for h in range(H)], "rewards": rewards,
             "next_phi": [sp.csr_matrix(nphi[:, h].reshape(K * A, D)) for h in range(H)],
             "n_actions": A}),
    }
    ragged = [[[0.5, 0.5]], [[0.2, 0.3, 0.5]]]
    bad_arrays = {"None": None, "'x'": "x", "ragged list": ragged, "0-size": np.zeros((0,)),
                  "wrong ndim": np.ones(3), "complex": phi.astype(complex)[..., :1],
                  "object array": np.array([None, 1], dtype=object), "NaN": np.full((K, H),
                                                                                    np.nan),
                  "dict": {}, "5": 5}
    cases = []
    for tag, (ctor, args) in base_args.items():
        for arg in args:
            for label, bad in bad_arrays.items():
                def run(ctor=ctor, args=args, arg=arg, bad=bad):
                    return ctor(**{**args, arg: bad})
                names = [arg] + (["phi", "feature_map"] if "states" in arg else [])
                cases.append(Case(f"constructor:{tag}", f"{arg}={label}", run, False, [names],
                                  lambda ds: _finite_weights(PEVI().fit(ds))))
    for arg, label, bad in (("horizon", "0", 0), ("n_features", "'3'", "3"),
                            ("n_actions", "None", None), ("dtype", "'int8'", "int8"),
                            ("next_form", "'half'", "half"), ("reward_noise", "nan", np.nan)):
        kw = {"horizon": H, "n_features": D, "n_actions": A, arg: bad}

        def run(kw=kw):
            with tempfile.TemporaryDirectory() as tmp:
                return DatasetWriter(Path(tmp) / "w", **kw)
        cases.append(Case("constructor:DatasetWriter", f"{arg}={label}", run, True, [[arg]]))
    for label, bad in (("None", None), ("5", 5), ("missing", "/nonexistent/r2pvi-ds")):
        cases.append(Case("constructor:open/load", f"OfflineDataset.open({label})",
                          lambda b=bad: OfflineDataset.open(b), True,
                          [["path", "/nonexistent", "NoneType", "int"]],
                          extra_types=(FileNotFoundError,)))
        cases.append(Case("constructor:open/load", f"OfflineDataset.load({label})",
                          lambda b=bad: OfflineDataset.load(b), True,
                          [["path", "/nonexistent", "NoneType", "int"]],
                          extra_types=(FileNotFoundError,)))
    return cases


def gym_cases() -> list[Case]:
    try:
        import gymnasium as gym
    except ImportError:  # pragma: no cover - the "envs" extra
        return []
    from r2pvi.evaluation import evaluate_policy

    cases = []
    for label, value in (("5", 5), ("-1", -1), ("0.5", 0.5), ("'left'", "left")):
        def run(value=value):
            return evaluate_policy(gym.make("CartPole-v1"), lambda h, o: np.full(
                len(o), value, dtype=object if isinstance(value, str) else None), 2, seed=0,
                max_steps=5)
        cases.append(Case("rollout:gymnasium", f"policy returns {label}", run, True,
                          [["action"], ["Discrete(2)"]]))
    return cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--show", action="append",
                    help="list the cases of this class (repeatable; default: obscure, silent, "
                         "data loss)")
    ap.add_argument("--group", help="only the groups starting with this")
    args = ap.parse_args(argv)
    show = set(args.show or ["obscure", "silent", "data loss"])
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        cases: list[Case] = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for form, (ds, next_form) in datasets(np.random.default_rng(1)).items():
                template = ds.save(root / f"template-{form}", next_form=next_form)
                base = fit(OfflineDataset.open(template, feature_map=feature_map))
                cases += directory_cases(root, form, template, feature_map, base)
            stored = datasets(np.random.default_rng(1))["stored"][0]
            cases += npz_dataset_cases(root, stored, fit(stored))
            cases += model_cases(root, rng)
            cases += feature_map_cases(root, rng)
            cases += save_cases(root, rng)
            cases += estimator_cases(rng)
            cases += constructor_cases(rng)
            cases += gym_cases()
        if args.group:
            cases = [c for c in cases if c.group.startswith(args.group)]
        results = [(c, *classify(c)) for c in cases]
    classes = ["clear", "obscure", "silent", "data loss", "accepted"]
    by_group: dict = {}
    for c, cls, _ in results:
        by_group.setdefault(c.group.split(":")[0], Counter())[cls] += 1
    total = Counter(cls for _, cls, _ in results)
    print(f"{len(results)} cases")
    print(f"{'group':<14}" + "".join(f"{k:>11}" for k in classes))
    for g, cnt in by_group.items():
        print(f"{g:<14}" + "".join(f"{cnt[k]:>11}" for k in classes))
    print(f"{'total':<14}" + "".join(f"{total[k]:>11}" for k in classes))
    for cls in classes:
        if cls in show:
            listed = [(c, m) for c, k, m in results if k == cls]
            if listed:
                print(f"\n{cls} ({len(listed)}):")
                for c, m in listed:
                    print(f"  [{c.group}] {c.name}: {m[:300]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
