"""Fit time with 1 BLAS thread against all cores' threads, and the cost of limiting them.

Chooses r2pvi's default for a single fit (``R2PVI_BLAS_THREADS``): for every size, the
estimators are fitted round-robin with ``threadpool_limits(1)`` and with
``threadpool_limits(n)`` (n = the machine's cores), after a warm-up, and the median wall
times are compared in the same run. It also times entering and leaving the limit itself,
which a single fit pays when r2pvi limits the threads for it. Needs ``threadpoolctl``
(the ``experiments`` extra).

    python benchmarks/bench_threads.py --repeats 15
    python benchmarks/bench_threads.py --sizes 1000x10 10000x30 2000x120
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from bench_fit import make_dataset  # the same synthetic data (run from benchmarks/ or its parent)
from threadpoolctl import ThreadpoolController, threadpool_info

import r2pvi
from r2pvi._threads import _env_threads


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["1000x10", "1000x30", "10000x30",
                                                       "2000x120"], help="KxD list")
    parser.add_argument("--H", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=11)
    args = parser.parse_args(argv)
    if _env_threads() is not None:
        parser.error("unset R2PVI_BLAS_THREADS: this script compares thread counts itself")
    os.environ["R2PVI_BLAS_THREADS"] = "0"  # r2pvi leaves BLAS alone; this script limits it
    ctl = ThreadpoolController()
    n = os.cpu_count() or 1
    blas = [f"{i['internal_api']} {i.get('version')} ({i['num_threads']} threads)"
            for i in threadpool_info() if i["user_api"] == "blas"]
    print(f"cores: {n}; BLAS: {', '.join(blas)}; load average: {os.getloadavg()}")

    t0 = time.perf_counter()
    for _ in range(200):
        with ctl.limit(limits=1, user_api="blas"):
            pass
    print(f"entering + leaving threadpool_limits(1): {(time.perf_counter() - t0) / 200 * 1e3:.3f}"
          " ms per fit")

    print(f"\n{'K x d (H=' + str(args.H) + ')':<18}{'estimator':<12}{'1 thread':>12}"
          f"{str(n) + ' threads':>12}{'ratio':>8}")
    for size in args.sizes:
        K, d = (int(x) for x in size.lower().split("x"))
        ds, theta = make_dataset(K, args.H, d)
        ests = {"R2PVI-TV": r2pvi.R2PVI("tv", 1.0, reward_weights=theta),
                "R2PVI-KL": r2pvi.R2PVI("kl", 1.0, reward_weights=theta),
                "PEVI": r2pvi.PEVI(reward_weights=theta)}
        times = {(name, t): [] for name in ests for t in (1, n)}
        for est in ests.values():
            for t in (1, n):
                with ctl.limit(limits=t, user_api="blas"):
                    est.fit(ds)  # warm-up
        for _ in range(args.repeats):
            for name, est in ests.items():
                for t in (1, n):
                    with ctl.limit(limits=t, user_api="blas"):
                        s = time.perf_counter()
                        est.fit(ds)
                        times[(name, t)].append(time.perf_counter() - s)
        for name in ests:
            one = statistics.median(times[(name, 1)])
            many = statistics.median(times[(name, n)])
            print(f"{K} x {d:<11}{name:<12}{one * 1e3:>10.1f}ms{many * 1e3:>10.1f}ms"
                  f"{many / one:>8.2f}")
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
