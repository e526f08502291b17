"""Datasets bigger than memory: fits from disk, peak memory, and scaling in K.

Writes its data first (nothing is committed), then times each fit in a fresh process and
reports the process's peak resident memory (``VmHWM``; see :func:`peak_rss_mib`):

    python benchmarks/bench_storage.py disk --K 1000000          # features stored, float32
    python benchmarks/bench_storage.py disk --keep --repeats 3   # again, best of 3 each
    python benchmarks/bench_storage.py disk --K 500000 --dtype float64   # float64 storage
    python benchmarks/bench_storage.py scaling --Ks 1e5 1e6 1e7  # observations + feature map
    python benchmarks/bench_storage.py float32                   # float32 vs float64 storage
    python benchmarks/bench_storage.py behaviour --Ks 1e5 1e6    # next_form full vs behaviour

``disk``: K trajectories (d = 30, H = 20, A = 2, synthetic simplex features drawn in float32,
stored as ``--dtype``: float32 by default, or float64, twice the bytes) written with
``r2pvi.DatasetWriter`` to ``<dir>/features-K{K}-{dtype}`` (float32 data written under the
older name ``features-K{K}`` is reused by ``--keep``); then the time to read the whole
dataset once from the page cache (the second of two reads), and the fit time, CPU time (all
threads) and peak RSS of R2PVI-TV, -KL, -chi^2 and DRPVI on ``OfflineDataset.open(path)``.
The writer stores each step's Gram matrix with the data, so a TV step from disk is one pass
of matrix-vector products over its features. On a shared machine the CPU-time ratios are
the steadier ones; the load average is printed with every row.

``scaling``: stored 2-D observations (float32), int8 actions and a normalized-RBF x action
feature map (d = 30), written with ``OfflineDataset.from_observations(...).save(path)``;
then the R2PVI-TV fit time for each K. The features are computed chunk by chunk while
fitting (the Gram matrix and the regressions are accumulated by chunk: nothing of size K d is
held); the fitted model keeps the (H, K) next-state values.

``behaviour``: trajectories whose next state is the next step's state
(``phi[:, h+1] = next_phi[:, h, a_{h+1}]``, the behaviour action ``a_{h+1}`` uniform; d = 30,
H = 20, A = 2, float32), written by ``DatasetWriter`` with ``next_form="full"`` and
``next_form="behaviour"``; then the bytes on disk, the time to read each dataset once from the
page cache and the R2PVI-TV fit time of each (the weights must be bitwise equal).

Data goes to ``--dir`` (default ``/tmp/r2pvi-bench``); check ``df -h`` first: the K = 1e6
feature dataset takes 7.3 GB (14.7 GB in float64; a fair "read once" needs it in the page
cache, so check the free memory too), the K = 1e7 observation dataset 5 GB. ``--keep`` reuses data
already written.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

H, D, A = 20, 30, 2
CENTERS = np.stack(np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 3)), -1).reshape(-1, 2)
CX, CY = CENTERS[:, 0].copy(), CENTERS[:, 1].copy()


def rbf_action_map(obs, actions):
    """Normalized RBF on 2-D observations (15 centers, width^2 0.1), crossed with the action
    block-wise: d = 30, on the simplex. Vectorized without reductions over tiny axes."""
    x = np.asarray(obs, dtype=np.float64)
    actions = np.asarray(actions)
    n, m = x.shape[0], CX.size
    d2 = np.subtract.outer(x[:, 0], CX)
    d2 *= d2
    t = np.subtract.outer(x[:, 1], CY)
    t *= t
    d2 += t
    d2 *= -10.0
    z = np.exp(d2, out=d2)
    z /= z.sum(axis=1, keepdims=True)
    out = np.zeros((n, A, m))
    if n and np.all(actions == actions[0]):  # next states: one action for all rows
        out[:, int(actions[0])] = z
    else:
        out[np.arange(n), actions] = z
    return out.reshape(n, A * m)


def theta():
    return np.random.default_rng(123).uniform(0, 1, size=(H, D))


def estimator(name):
    import r2pvi
    from r2pvi.algorithms import DRPVI

    kw = {"reward_weights": theta(), "r_max": 1.0}
    return {
        "R2PVI-TV": lambda: r2pvi.R2PVI("tv", 1.0, **kw),
        "R2PVI-KL": lambda: r2pvi.R2PVI("kl", 1.0, **kw),
        "R2PVI-chi2": lambda: r2pvi.R2PVI("chi2", 1.0, **kw),
        "DRPVI": lambda: DRPVI(0.1, **kw),
    }[name]()


# ----------------------------------------------------------------------------- writing
def write_features(path: Path, K: int, chunk: int = 20_000, seed: int = 0,
                   dtype: str = "float32"):
    """The ``disk`` data; the same (float32-drawn) numbers whatever the storage ``dtype``."""
    from r2pvi import DatasetWriter

    rng = np.random.default_rng(seed)
    th = theta()
    with DatasetWriter(path, horizon=H, n_features=D, n_actions=A, dtype=dtype,
                       overwrite=True) as w:
        for s in range(0, K, chunk):
            k = min(chunk, K - s)
            phi = rng.random((k, H, D), dtype=np.float32)
            phi /= phi.sum(-1, keepdims=True)
            nphi = rng.random((k, H, A, D), dtype=np.float32)
            nphi /= nphi.sum(-1, keepdims=True)
            rewards = np.einsum("khd,hd->kh", phi, th)
            w.append(phi, rewards, nphi)


def write_trajectories(path: Path, K: int, next_form: str, chunk: int = 20_000, seed: int = 0):
    """Trajectories: the next state of step h is the state of step h+1 (see ``behaviour``)."""
    from r2pvi import DatasetWriter

    rng = np.random.default_rng(seed)
    th = theta()
    with DatasetWriter(path, horizon=H, n_features=D, n_actions=A, dtype="float32",
                       overwrite=True, next_form=next_form) as w:
        for s in range(0, K, chunk):
            k = min(chunk, K - s)
            nphi = rng.random((k, H, A, D), dtype=np.float32)
            nphi /= nphi.sum(-1, keepdims=True)
            phi = np.empty((k, H, D), dtype=np.float32)
            phi[:, 0] = rng.random((k, D), dtype=np.float32)
            phi[:, 0] /= phi[:, 0].sum(-1, keepdims=True)
            taken = rng.integers(A, size=(k, H - 1))  # the behaviour actions a_1 .. a_{H-1}
            phi[:, 1:] = nphi[np.arange(k)[:, None], np.arange(H - 1), taken]
            rewards = np.einsum("khd,hd->kh", phi, th)
            w.append(phi, rewards, nphi)


def write_observations(path: Path, K: int, seed: int = 0):
    from r2pvi import OfflineDataset

    scratch = path.with_name(path.name + ".scratch")
    scratch.mkdir(parents=True, exist_ok=True)
    mm = np.lib.format.open_memmap
    obs = mm(scratch / "obs.npy", "w+", np.float32, (H, K, 2))
    nobs = mm(scratch / "nobs.npy", "w+", np.float32, (H, K, 2))
    act = mm(scratch / "act.npy", "w+", np.int8, (H, K))
    rew = mm(scratch / "rew.npy", "w+", np.float64, (H, K))
    rng = np.random.default_rng(seed)
    step = 1_000_000
    for s in range(0, K, step):
        e = min(K, s + step)
        x = rng.random((e - s, 2), dtype=np.float32)
        for h in range(H):  # a noisy drift, so the next observation is the next state
            a = rng.integers(A, size=e - s, dtype=np.int8)
            nx = np.clip(x + 0.1 * (a[:, None] - 0.5) + 0.05 * rng.standard_normal(
                (e - s, 2), dtype=np.float32), 0, 1)
            obs[h, s:e], act[h, s:e], nobs[h, s:e] = x, a, nx
            rew[h, s:e] = x[:, 0]
            x = nx
    for m in (obs, nobs, act, rew):
        m.flush()
    ds = OfflineDataset.from_observations(obs.swapaxes(0, 1), act.swapaxes(0, 1),
                                          rew.swapaxes(0, 1), nobs.swapaxes(0, 1),
                                          rbf_action_map, A)
    ds.save(path, overwrite=True)
    del ds, obs, nobs, act, rew
    shutil.rmtree(scratch)


def dir_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir())


# ----------------------------------------------------------------------------- children
def child(task: dict) -> dict:
    from threadpoolctl import threadpool_limits

    from r2pvi import OfflineDataset
    from r2pvi.storage import CHUNK, FileField, RowFile

    threadpool_limits(task["blas_threads"])
    path = Path(task["path"])
    t0, c0 = time.perf_counter(), time.process_time()
    if task["what"] == "read":  # every file once, by chunk into one reused buffer
        total = 0
        for f in sorted(path.glob("*.npy")):
            if f.name.startswith("next_side"):  # the behaviour form's side table: (n, ...)
                rows = RowFile(f)
                for s in range(0, rows.shape[0], CHUNK * 20):
                    total += rows.read(s, min(rows.shape[0], s + CHUNK * 20)).nbytes
                continue
            field = FileField(f)
            buf = np.empty((min(CHUNK, field.shape[1]),) + field.shape[2:], field.dtype)
            for h in range(field.shape[0]):
                for s in range(0, field.shape[1], CHUNK):
                    e = min(field.shape[1], s + CHUNK)
                    total += field.read(h, s, e, out=buf[: e - s]).nbytes
        out = {"bytes": total}
    else:
        fmap = rbf_action_map if task.get("map") else None
        ds = OfflineDataset.open(path, feature_map=fmap)
        est = estimator(task["what"]).fit(ds)
        out = {"weights_sum": float(est.weights_.sum()),
               "weights_hex": est.weights_.tobytes().hex()}
    out["seconds"] = time.perf_counter() - t0
    out["cpu_seconds"] = time.process_time() - c0  # every thread of the process
    out["load"] = os.getloadavg()[0]
    out["peak_rss_mib"] = peak_rss_mib()
    return out


def peak_rss_mib() -> float:
    """This process's peak resident memory: ``VmHWM`` (Linux; it starts afresh at exec), else
    ``ru_maxrss``, which on Linux carries over the parent's peak through fork and exec (a
    child of a parent that wrote the data would report the parent's memory)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


BLAS_THREADS = 1


def run_child(**task) -> dict:
    task["blas_threads"] = BLAS_THREADS
    res = subprocess.run([sys.executable, __file__, "--child", json.dumps(task)],
                         capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- main
def features_path(root: Path, K: int, dtype: str, keep: bool) -> Path:
    """``features-K{K}-{dtype}``; with ``keep``, float32 data written under the older name
    ``features-K{K}`` (before ``--dtype``) is reused when the new name does not exist."""
    path = root / f"features-K{K}-{dtype}"
    legacy = root / f"features-K{K}"
    if (keep and dtype == "float32" and not (path / "manifest.json").exists()
            and (legacy / "manifest.json").exists()
            and json.loads((legacy / "manifest.json").read_text()).get("dtype") == dtype):
        return legacy
    return path


def disk(args):
    path = features_path(Path(args.dir), args.K, args.dtype, args.keep)
    if not (args.keep and (path / "manifest.json").exists()):
        from threadpoolctl import threadpool_limits

        t0 = time.perf_counter()
        with threadpool_limits(BLAS_THREADS):  # the writer forms each step's Gram matrix
            write_features(path, args.K, dtype=args.dtype)
        print(f"wrote {path} in {time.perf_counter() - t0:.1f} s")
    size = dir_size(path)
    print(f"K = {args.K}, d = {D}, H = {H}, A = {A}, {args.dtype} on disk: "
          f"{size / 2**30:.2f} GiB ({path})")
    run_child(what="read", path=str(path))  # warm the page cache
    read = best_of(args.repeats, what="read", path=str(path))
    print(f"{'task':<12} {'seconds':>8} {'x read':>7} {'CPU s':>7} {'x read':>7} "
          f"{'peak RSS MiB':>13} {'load':>5}"
          + (f"   (best of {args.repeats} fresh processes each)" if args.repeats > 1 else ""))

    def row(name, r):
        print(f"{name:<12} {r['seconds']:8.2f} {r['seconds'] / read['seconds']:7.2f} "
              f"{r['cpu_seconds']:7.2f} {r['cpu_seconds'] / read['cpu_seconds']:7.2f} "
              f"{r['peak_rss_mib']:13.0f} {r['load']:5.1f}", flush=True)

    row("read once", read)
    for name in args.estimators:
        row(name, best_of(args.repeats, what=name, path=str(path)))


def best_of(repeats: int, **task) -> dict:
    """The run with the least CPU time among ``repeats`` fresh processes (each field from that
    run; the peak memory is the largest seen): on a shared machine the least disturbed run."""
    runs = [run_child(**task) for _ in range(max(1, repeats))]
    best = dict(min(runs, key=lambda r: r["cpu_seconds"]))
    best["seconds"] = min(r["seconds"] for r in runs)
    best["peak_rss_mib"] = max(r["peak_rss_mib"] for r in runs)
    return best


def scaling(args):
    print(f"observations (2-D float32) + RBF x action feature map, d = {D}, H = {H}, A = {A}")
    print(f"{'K':>10} {'GiB':>6} {'fit s':>8} {'us / traj':>10} {'CPU us / traj':>14} "
          f"{'peak RSS MiB':>13} {'load':>5}")
    for K in (int(float(k)) for k in args.Ks):
        path = Path(args.dir) / f"obs-K{K}"
        if not (args.keep and (path / "manifest.json").exists()):
            write_observations(path, K)
        r = run_child(what="R2PVI-TV", path=str(path), map=True)
        print(f"{K:>10} {dir_size(path) / 2**30:6.2f} {r['seconds']:8.1f} "
              f"{1e6 * r['seconds'] / K:10.2f} {1e6 * r['cpu_seconds'] / K:14.2f} "
              f"{r['peak_rss_mib']:13.0f} {r['load']:5.1f}", flush=True)


def behaviour(args):
    """Bytes on disk and TV fit time of the full and the behaviour next-state form."""
    print(f"trajectories, d = {D}, H = {H}, A = {A}, float32; R2PVI-TV from disk (page cache)")
    print(f"{'K':>8} {'form':>9} {'write s':>8} {'GiB':>6} {'x full':>6} {'read s':>7} "
          f"{'read CPU':>8} {'TV s':>6} {'TV CPU':>7} {'x read':>6} {'RSS MiB':>8} {'load':>5}",
          flush=True)
    for K in (int(float(k)) for k in args.Ks):
        fits, sizes = {}, {}
        for form in ("full", "behaviour"):
            path = Path(args.dir) / f"traj-{form}-K{K}"
            wrote = float("nan")
            if not (args.keep and (path / "manifest.json").exists()):
                from threadpoolctl import threadpool_limits

                t0 = time.perf_counter()
                with threadpool_limits(BLAS_THREADS):
                    write_trajectories(path, K, form)
                wrote = time.perf_counter() - t0
            sizes[form] = dir_size(path)
            run_child(what="read", path=str(path))  # warm the page cache
            read = run_child(what="read", path=str(path))
            fits[form] = r = run_child(what="R2PVI-TV", path=str(path))
            print(f"{K:>8} {form:>9} {wrote:8.1f} {sizes[form] / 2**30:6.2f} "
                  f"{sizes[form] / sizes['full']:6.3f} {read['seconds']:7.2f} "
                  f"{read['cpu_seconds']:8.2f} {r['seconds']:6.2f} {r['cpu_seconds']:7.2f} "
                  f"{r['seconds'] / read['seconds']:6.2f} {r['peak_rss_mib']:8.0f} "
                  f"{r['load']:5.1f}", flush=True)
        same = fits["full"]["weights_hex"] == fits["behaviour"]["weights_hex"]
        print(f"{K:>8} TV weights bitwise equal across the forms: {same}", flush=True)
        if not args.keep:
            for form in fits:
                shutil.rmtree(Path(args.dir) / f"traj-{form}-K{K}")


def float32(args):
    """float32 storage against float64 on bench_fit.py's data (K = 1e4, d = 30, H = 20)."""
    sys.path.insert(0, str(Path(__file__).parent))
    import bench_fit

    from r2pvi import OfflineDataset

    ds, th = bench_fit.make_dataset(args.K, H, D)
    f32 = OfflineDataset.from_features(ds.phi, ds.rewards, ds.next_phi, dtype="float32")
    print(f"K = {args.K}, d = {D}, H = {H}: weights with float32 storage vs float64")
    for name in ("R2PVI-TV", "R2PVI-KL", "R2PVI-chi2", "DRPVI"):
        a, b = estimator(name).fit(ds), estimator(name).fit(f32)
        print(f"{name:<11} max |w32 - w64| = {np.abs(a.weights_ - b.weights_).max():.2e}"
              f"  (max |w| = {np.abs(a.weights_).max():.2f})")


def main(argv=None):
    if argv is None and len(sys.argv) > 2 and sys.argv[1] == "--child":
        print(json.dumps(child(json.loads(sys.argv[2]))))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("disk")
    d.add_argument("--K", type=int, default=1_000_000)
    d.add_argument("--estimators", nargs="*",
                   default=["R2PVI-TV", "R2PVI-KL", "R2PVI-chi2", "DRPVI"])
    d.add_argument("--repeats", type=int, default=1,
                   help="fresh processes per task; the least CPU time is reported (and the "
                   "least wall time)")
    d.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                   help="storage type of the features (float64: 2x the bytes; the fit reads "
                   "the mapped pages with no copy)")
    s = sub.add_parser("scaling")
    s.add_argument("--Ks", nargs="*", default=["1e5", "1e6", "1e7"])
    b = sub.add_parser("behaviour")
    b.add_argument("--Ks", nargs="*", default=["1e5", "1e6"])
    for p in (d, s, b):
        p.add_argument("--dir", default=os.environ.get("R2PVI_BENCH_DIR", "/tmp/r2pvi-bench"))
        p.add_argument("--keep", action="store_true", help="reuse data already written")
        p.add_argument("--blas-threads", type=int, default=1,
                       help="BLAS threads in the fits (1: stable timings on a shared machine)")
    f = sub.add_parser("float32")
    f.add_argument("--K", type=int, default=10_000)
    f.add_argument("--blas-threads", type=int, default=1)
    args = ap.parse_args(argv)
    global BLAS_THREADS
    BLAS_THREADS = args.blas_threads
    {"disk": disk, "scaling": scaling, "float32": float32,
     "behaviour": behaviour}[args.cmd](args)


if __name__ == "__main__":
    main()
