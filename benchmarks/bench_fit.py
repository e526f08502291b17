"""Fit time of every estimator against the floor of unavoidable dense linear algebra.

Synthetic data: K trajectories, d features, H steps, two actions (the size of the issue's
speed target and of the authors' timing figure). The floor is what any implementation of
the paper must do: the H Gram matrices (with their Cholesky factors) and H ridge solves,
timed in this same run. Each timing is the median of ``--repeats`` rounds in which every
estimator is fitted once (round-robin, after one warm-up fit each).

    python benchmarks/bench_fit.py                 # K=10000, d=30, H=20
    python benchmarks/bench_fit.py --K 2000 --d 60
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import r2pvi
from r2pvi._threads import limit_blas
from r2pvi.algorithms import DRPVI, DRVIL
from r2pvi.duals.operators import RidgeExpectation, cholesky_gram


def make_dataset(K, H, d, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    theta = rng.uniform(0, 1, size=(H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    return r2pvi.OfflineDataset.from_features(phi, rewards, next_phi), theta


def floor_fit(ds, gamma=1.0):
    """The H Gram matrices (Cholesky-factored) and the H ridge solves, with the BLAS threads
    of a fit (one unless ``R2PVI_BLAS_THREADS`` says otherwise), so the ratios compare like
    with like."""
    with limit_blas():
        for h in range(ds.horizon):
            phi, rewards, _, _ = ds.step(h)
            RidgeExpectation(phi, cholesky_gram(phi, gamma))(rewards)


def interleaved_medians(fns: dict, repeats: int) -> dict:
    """Median wall time of each function, timed round-robin (one warm-up call each first) so
    that every ratio compares runs made under the same machine conditions."""
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def estimators(theta):
    kw = {"reward_weights": theta, "r_max": 1.0}
    return {
        "PEVI": r2pvi.PEVI(**kw),
        "R2PVI-TV": r2pvi.R2PVI("tv", 1.0, **kw),
        "R2PVI-KL": r2pvi.R2PVI("kl", 1.0, **kw),
        "R2PVI-chi2": r2pvi.R2PVI("chi2", 1.0, **kw),
        "DRPVI": DRPVI(0.1, **kw),
        "DRVI-L": DRVIL(0.1, **kw),
        "VA-DRPVI": DRPVI(0.1, variance_aware=True, **kw),
        "VA-R2PVI-TV": r2pvi.R2PVI("tv", 1.0, variance_aware=True, **kw),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--K", type=int, default=10_000)
    ap.add_argument("--d", type=int, default=30)
    ap.add_argument("--H", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--only", nargs="*", help="estimator names to time")
    args = ap.parse_args(argv)
    ds, theta = make_dataset(args.K, args.H, args.d)
    fns = {"floor": lambda: floor_fit(ds)}
    for name, est in estimators(theta).items():
        if not args.only or name in args.only or name == "R2PVI-TV":
            fns[name] = lambda est=est: est.fit(ds)
    med = interleaved_medians(fns, args.repeats)
    floor, tv = med.pop("floor"), med["R2PVI-TV"]
    print(f"K={args.K} d={args.d} H={args.H} A=2; median of {args.repeats} interleaved rounds")
    print(f"{'':<20s} {'fit time':>10s} {'/ floor':>8s} {'/ R2PVI-TV':>11s}")
    print(f"{'floor':<20s} {floor * 1e3:8.1f} ms {1:7.2f}x {floor / tv:10.2f}x")
    for name, t in med.items():
        print(f"{name:<20s} {t * 1e3:8.1f} ms {t / floor:7.2f}x {t / tv:10.2f}x")
    print("floor = the H Gram matrices with their Cholesky factors and the H ridge solves")


if __name__ == "__main__":
    main()
