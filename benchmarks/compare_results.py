"""Snapshot the library's results and compare two snapshots (refactors must not move them).

A snapshot holds the fitted weights of a fixed set of fits -- every estimator, on every
storage kind (memory, float32 and float64 directories, Dask arrays, sparse rows, observations
with a feature map), per-step and pooled -- and the non-timing rows of ``r2pvi reproduce
all``. ``compare`` says, per entry, whether two snapshots agree bitwise, to 1e-12 relative,
or not at all::

    python benchmarks/compare_results.py snapshot /tmp/before            # on the old code
    python benchmarks/compare_results.py snapshot /tmp/after             # on the new code
    python benchmarks/compare_results.py compare /tmp/before /tmp/after

``--no-reproduce`` skips ``reproduce all`` (the fits alone take a few seconds). Only public
names are used, so the script runs unchanged across moves of private code.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

TIMING_KEYS = ("seconds", "time", "elapsed", "wall", "cpu", "ms")


def _datasets(tmp: Path):
    """``{name: OfflineDataset}`` over every storage kind, from one seeded dataset."""
    import r2pvi
    from r2pvi import OfflineDataset

    rng = np.random.default_rng(20261205)
    K, H, d, A = 400, 4, 5, 3
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    rewards = rng.uniform(size=(K, H))
    nv = np.full((K, H, A), np.nan)
    nv[rng.uniform(size=(K, H)) < 0.05] = 0.0  # absorbing next states, known value 0
    out = {"memory": OfflineDataset.from_features(phi, rewards, next_phi, nv)}
    for dtype in ("float64", "float32"):
        p = tmp / f"dir-{dtype}"
        out["memory"].save(p, dtype=dtype)
        out[f"directory-{dtype}"] = OfflineDataset.open(p)
    try:
        import dask.array as da

        out["dask"] = OfflineDataset.from_dask(
            da.from_array(phi, chunks=(128, H, d)), da.from_array(rewards, chunks=(128, H)),
            da.from_array(next_phi, chunks=(128, H, A, d)),
            da.from_array(nv, chunks=(128, H, A)))
    except ImportError:  # pragma: no cover
        pass
    # observations + a feature map (tabular one-hot of (state, action) mixed into d)
    S = 7
    table = rng.dirichlet(np.ones(d), size=(S, A))
    states = rng.integers(S, size=(K, H))
    actions = rng.integers(A, size=(K, H))
    next_states = rng.integers(S, size=(K, H))
    rw = rng.uniform(size=(K, H))

    def fmap(s, a):
        return table[np.asarray(s, dtype=int), np.asarray(a, dtype=int)]

    out["observations"] = OfflineDataset.from_observations(
        states, actions, rw, next_states, fmap, A)
    out["transitions"] = OfflineDataset.from_transitions(
        states, actions, rw, next_states, fmap, A)
    try:
        import scipy.sparse as sp

        sparse_cls = getattr(r2pvi, "SparseOfflineDataset", None)
        if sparse_cls is None:
            from r2pvi.sparse import SparseOfflineDataset as sparse_cls  # noqa: N813
        rows = [sp.csr_matrix(phi[:, h]) for h in range(H)]
        nrows = [sp.csr_matrix(next_phi[:, h].reshape(K * A, d)) for h in range(H)]
        out["sparse"] = sparse_cls.from_rows(rows, rewards, nrows, A)
    except ImportError:  # pragma: no cover
        pass
    return out


def _estimators():
    from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, cressie_read

    ests = {
        "PEVI": lambda th: PEVI(beta=0.1, time_homogeneous=th),
        "PEVI-l1": lambda th: PEVI(beta=0.1, penalty="l1", time_homogeneous=th),
        "TV": lambda th: R2PVI("tv", 0.3, beta=0.1, time_homogeneous=th),
        "VA-TV": lambda th: R2PVI("tv", 0.3, beta=0.1, variance_aware=True,
                                  time_homogeneous=th),
        "KL": lambda th: R2PVI("kl", 0.3, beta=0.1, time_homogeneous=th),
        "KL-paper": lambda th: R2PVI("kl", 0.3, beta=0.1, kl_form="paper",
                                     time_homogeneous=th),
        "chi2": lambda th: R2PVI("chi2", 0.3, beta=0.1, time_homogeneous=th),
        "hellinger": lambda th: R2PVI("hellinger", 0.3, beta=0.1, time_homogeneous=th),
        "cressie2": lambda th: R2PVI(cressie_read(2.0), 0.3, beta=0.1, time_homogeneous=th),
        "DRPVI": lambda th: DRPVI(0.2, beta=0.1, time_homogeneous=th),
        "DRVIL": lambda th: DRVIL(0.2, beta=0.1, time_homogeneous=th),
        "DRVIL-ma": lambda th: DRVIL(0.2, beta=0.1, form="ma", time_homogeneous=th),
    }
    return ests


def snapshot_fits(out: Path) -> dict:
    arrays, errors = {}, {}
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = _datasets(Path(tmp))
        for dname, ds in data.items():
            for ename, make in _estimators().items():
                for th in (False, True):
                    key = f"{dname}/{ename}/{'pooled' if th else 'per-step'}"
                    try:
                        arrays[key] = np.asarray(make(th).fit(ds).weights_, dtype=np.float64)
                    except Exception as exc:  # an error is a result too: it must not move
                        errors[key] = f"{type(exc).__name__}: {exc}"
    np.savez(out / "fits.npz", **arrays)
    (out / "fit_errors.json").write_text(json.dumps(errors, indent=1, sort_keys=True))
    return {"fits": len(arrays), "errors": len(errors)}


def snapshot_reproduce(out: Path) -> None:
    rdir = out / "reproduce"
    subprocess.run([sys.executable, "-m", "r2pvi", "reproduce", "all", "--out", str(rdir),
                    "--no-progress", "--no-plot"], check=True, stdout=subprocess.DEVNULL)


def _strip_timing(row):
    if isinstance(row, dict):
        return {k: _strip_timing(v) for k, v in row.items()
                if not any(t in k.lower() for t in TIMING_KEYS)}
    if isinstance(row, list):
        return [_strip_timing(v) for v in row]
    return row


def _rows(path: Path) -> dict | None:
    """``{path: value}`` of a result file's rows, or None for a file whose unit is time."""
    doc = json.loads(path.read_text())
    if str(doc.get("unit", "")).lower() in ("s", "ms", "seconds"):
        return None
    return dict(_leaves(_strip_timing(doc.get("rows", []))))


def _leaves(obj, prefix=""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, f"{prefix}/{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _leaves(v, f"{prefix}[{i}]")
    else:
        yield prefix, obj


def _close(a, b, rtol=1e-12) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        return False
    scale = np.maximum(np.abs(a), np.abs(b))
    same_nan = np.isnan(a) & np.isnan(b)
    return bool(np.all(same_nan | (np.abs(a - b) <= rtol * np.maximum(scale, 1e-300))))


def compare(a: Path, b: Path) -> int:
    bad = 0
    fa, fb = np.load(a / "fits.npz"), np.load(b / "fits.npz")
    keys = sorted(set(fa.files) | set(fb.files))
    counts = {"bitwise": 0, "1e-12": 0, "differ": 0, "missing": 0}
    for k in keys:
        if k not in fa.files or k not in fb.files:
            counts["missing"] += 1
            print(f"missing  {k}")
            continue
        x, y = fa[k], fb[k]
        if x.shape == y.shape and np.array_equal(x, y, equal_nan=True):
            counts["bitwise"] += 1
        elif _close(x, y):
            counts["1e-12"] += 1
        else:
            counts["differ"] += 1
            diff = np.nanmax(np.abs(x - y)) if x.shape == y.shape else math.inf
            print(f"DIFFER   {k}: max |diff| {diff:.3g}")
    ea = json.loads((a / "fit_errors.json").read_text())
    eb = json.loads((b / "fit_errors.json").read_text())
    if ea != eb:
        print(f"fit errors differ: {sorted(set(ea.items()) ^ set(eb.items()))}")
        bad += 1
    print(f"fits: {counts}")
    bad += counts["differ"] + counts["missing"]
    ra, rb = a / "reproduce", b / "reproduce"
    if ra.exists() and rb.exists():
        rc = {"bitwise": 0, "1e-12": 0, "differ": 0}
        for ja in sorted(ra.glob("*.json")):
            jb = rb / ja.name
            if not jb.exists():
                print(f"missing  reproduce/{ja.name}")
                bad += 1
                continue
            la, lb = _rows(ja), _rows(jb)
            if la is None or lb is None:  # a timing figure (fig2a/b): its values are times
                print(f"skipped  reproduce/{ja.name} (its values are timings)")
                continue
            for k in sorted(set(la) | set(lb)):
                va, vb = la.get(k), lb.get(k)
                if va == vb:
                    rc["bitwise"] += 1
                elif (isinstance(va, int | float) and isinstance(vb, int | float)
                      and _close(va, vb)):
                    rc["1e-12"] += 1
                else:
                    rc["differ"] += 1
                    print(f"DIFFER   reproduce/{ja.name}{k}: {va!r} vs {vb!r}")
        print(f"reproduce all rows: {rc}")
        bad += rc["differ"]
    print("SAME" if bad == 0 else f"DIFFERENT ({bad})")
    return 0 if bad == 0 else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("snapshot")
    s.add_argument("out", type=Path)
    s.add_argument("--no-reproduce", action="store_true")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "snapshot":
        args.out.mkdir(parents=True, exist_ok=True)
        print(snapshot_fits(args.out))
        if not args.no_reproduce:
            snapshot_reproduce(args.out)
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
