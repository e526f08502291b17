"""Fit time of every estimator against the floor of unavoidable dense linear algebra.

Synthetic data: K trajectories, d features, H steps, two actions (the size of the issue's
speed target and of the authors' timing figure). The floor is what any implementation of
the paper must do: the H Gram matrices (with their Cholesky factors) and H ridge solves,
timed in this same run. Each timing is the median of ``--repeats`` rounds in which every
estimator is fitted once (round-robin, after one warm-up fit each). The "paired" columns
are the median over the rounds of the ratio within a round (each fit against the floor or
R2PVI-TV timed seconds apart): steadier than the ratio of medians when the machine's speed
drifts during the run.

    python benchmarks/bench_fit.py                 # K=10000, d=30, H=20
    python benchmarks/bench_fit.py --K 2000 --d 60
    python benchmarks/bench_fit.py --baseline /tmp/old/src   # also time another source tree

``--baseline`` takes a directory holding another version's ``r2pvi`` package (e.g. from
``git archive <rev> src | tar -x -C /tmp/old``), imports it under another name and times it
in the same rounds, so that old and new ratios come from one run.
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import r2pvi
from r2pvi._threads import limit_blas
from r2pvi.algorithms import DRPVI, DRVIL
from r2pvi.duals import RidgeExpectation, cholesky_gram


def make_dataset(K, H, d, A=2, seed=0, package=r2pvi):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    theta = rng.uniform(0, 1, size=(H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    return package.OfflineDataset.from_features(phi, rewards, next_phi), theta


def floor_fit(ds, gamma=1.0, package=None):
    """The H Gram matrices (Cholesky-factored) and the H ridge solves, with the BLAS threads
    of a fit (one unless ``R2PVI_BLAS_THREADS`` says otherwise), so the ratios compare like
    with like. ``package``: another version's r2pvi (``--baseline``), None for this one."""
    if package is None:
        ridge, gram, blas = RidgeExpectation, cholesky_gram, limit_blas
    else:
        ops = importlib.import_module(package.__name__ + ".duals")  # every version's names
        ridge, gram = ops.RidgeExpectation, ops.cholesky_gram
        blas = importlib.import_module(package.__name__ + "._threads").limit_blas
    with blas():
        for h in range(ds.horizon):
            phi, rewards, _, _ = ds.step(h)
            ridge(phi, gram(phi, gamma))(rewards)


def forget_grams(ds):
    """The dataset without the Gram matrices an earlier fit left in its cache (r2pvi keeps
    them for repeated fits on the same data): every timed fit forms its own, as a single fit
    does, so that it is compared with a floor that forms them too."""
    src = getattr(ds, "_source", None)
    for name in ("_grams", "_sums"):  # the Gram matrices and the column sums Phi^T 1
        cache = getattr(src, name, None)
        if cache is not None:
            cache[:] = [None] * len(cache)
    return ds


def import_baseline(src: str):
    """Another version's ``r2pvi`` package (``src/r2pvi``) imported as ``r2pvi_baseline``
    (its imports are relative, so a renamed copy is a separate package)."""
    root = Path(src)
    pkg = root / "r2pvi" if (root / "r2pvi").is_dir() else root
    if not (pkg / "__init__.py").exists():
        raise ValueError(f"--baseline must be a directory holding the r2pvi package, got {src}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_fit_"))
    shutil.copytree(pkg, tmp / "r2pvi_baseline")
    sys.path.insert(0, str(tmp))
    return importlib.import_module("r2pvi_baseline")


def interleaved_times(fns: dict, repeats: int, clock=time.perf_counter) -> dict:
    """Every round's time of each function (wall time, or ``clock``), timed round-robin (one
    warm-up call each first) so that every ratio compares runs made under the same machine
    conditions."""
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = clock()
            fn()
            times[name].append(clock() - t0)
    return times


def interleaved_medians(fns: dict, repeats: int, clock=time.perf_counter) -> dict:
    """Median time of each function over interleaved rounds (:func:`interleaved_times`)."""
    return {name: statistics.median(t)
            for name, t in interleaved_times(fns, repeats, clock).items()}


def paired_ratio(times: dict, name: str, ref: str) -> float:
    """Median over the rounds of ``name``'s time over ``ref``'s time in the same round: a
    paired comparison, insensitive to the machine's speed drifting between rounds."""
    return statistics.median(a / b for a, b in zip(times[name], times[ref], strict=True))


def estimators(theta, package=None):
    kw = {"reward_weights": theta, "r_max": 1.0}
    if package is None:
        r, drpvi, drvil = r2pvi, DRPVI, DRVIL
    else:
        r = package
        algs = importlib.import_module(package.__name__ + ".algorithms")
        drpvi, drvil = algs.DRPVI, algs.DRVIL
    return {
        "PEVI": r.PEVI(**kw),
        "R2PVI-TV": r.R2PVI("tv", 1.0, **kw),
        "R2PVI-KL": r.R2PVI("kl", 1.0, **kw),
        "R2PVI-chi2": r.R2PVI("chi2", 1.0, **kw),
        "DRPVI": drpvi(0.1, **kw),
        "DRVI-L": drvil(0.1, **kw),
        "VA-DRPVI": drpvi(0.1, variance_aware=True, **kw),
        "VA-R2PVI-TV": r.R2PVI("tv", 1.0, variance_aware=True, **kw),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--K", type=int, default=10_000)
    ap.add_argument("--d", type=int, default=30)
    ap.add_argument("--H", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=21,
                    help="interleaved rounds (default 21: on a shared 2-core machine the ratio "
                    "of two fits swings by 5-10%% between runs of 7 rounds)")
    ap.add_argument("--only", nargs="*", help="estimator names to time")
    ap.add_argument("--baseline", help="directory of another version's r2pvi package (its "
                    "src/), timed in the same rounds")
    ap.add_argument("--cpu", action="store_true",
                    help="CPU time of this process instead of wall time (with one BLAS thread, "
                    "the work done: insensitive to other jobs and to preemption)")
    args = ap.parse_args(argv)
    versions = {"": None}
    if args.baseline:
        versions["baseline "] = import_baseline(args.baseline)
    fns = {}
    for label, package in versions.items():
        ds, theta = make_dataset(args.K, args.H, args.d, package=package or r2pvi)
        fns[label + "floor"] = lambda ds=ds, package=package: floor_fit(ds, package=package)
        for name, est in estimators(theta, package).items():
            if not args.only or name in args.only or name == "R2PVI-TV":
                fns[label + name] = lambda est=est, ds=ds: est.fit(forget_grams(ds))
    clock = time.process_time if args.cpu else time.perf_counter
    times = interleaved_times(fns, args.repeats, clock)
    med = {name: statistics.median(t) for name, t in times.items()}
    print(f"K={args.K} d={args.d} H={args.H} A=2; median of {args.repeats} interleaved rounds"
          f" ({'CPU' if args.cpu else 'wall'} time)")
    for label in versions:
        floor, tv = med[label + "floor"], med[label + "R2PVI-TV"]
        print(f"{label + 'fit':<20s} {'time':>10s} {'/ floor':>8s} {'/ R2PVI-TV':>11s}"
              f"  paired: {'/ floor':>7s} {'/ TV':>6s}")
        for name, t in med.items():
            if name.startswith(label) and (label or not name.startswith("baseline ")):
                print(f"{name:<20s} {t * 1e3:8.1f} ms {t / floor:7.2f}x {t / tv:10.2f}x"
                      f"          {paired_ratio(times, name, label + 'floor'):6.2f}x"
                      f" {paired_ratio(times, name, label + 'R2PVI-TV'):5.2f}x")
    if args.baseline:  # each estimator against its baseline version, round by round
        print(f"{'this / baseline':<20s} {'paired':>10s}")
        for name in med:
            if not name.startswith("baseline ") and "baseline " + name in times:
                print(f"{name:<20s} {paired_ratio(times, name, 'baseline ' + name):9.3f}x")
    print("floor = the H Gram matrices with their Cholesky factors and the H ridge solves; "
          "paired = median over the rounds of the ratio within each round")


if __name__ == "__main__":
    main()
