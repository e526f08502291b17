"""Fit time of Dask arrays on a ``distributed`` cluster against the same data in memory.

Builds seeded ``phi``, ``rewards``, ``next_phi`` with NumPy, wraps them with
``dask.array.from_array`` (chunks along trajectories), starts
``LocalCluster(processes=True, n_workers=2, threads_per_worker=1)`` and a ``Client``, and
fits ``R2PVI('kl')`` and ``R2PVI('tv')`` from ``OfflineDataset.from_dask`` (the arrays as
given, and persisted on the cluster first; the latter also a second time, its step-major view
already persisted by a first fit) and from ``OfflineDataset.from_features``. Prints
wall and CPU (client process) seconds, the ratio to the in-memory fit, whether
``distributed`` warned of a large graph, and the largest weight difference::

    python benchmarks/bench_dask_cluster.py                          # K = 2e5, H = 10, d = 30
    python benchmarks/bench_dask_cluster.py --K 1000000 --H 20 --d 30 --disk /tmp/dask-1e6

With ``--disk DIR`` the data never sit in the client: a float32 dataset directory is written
once at ``DIR`` (:class:`~r2pvi.DatasetWriter`, a chunk of trajectories at a time; reused when
it exists), the in-memory fit opens it (:meth:`~r2pvi.OfflineDataset.open`: the files mapped,
served from the page cache after the first read), and the workers read their own chunks of
the same files (as in docs/scale-out.md). That is how the target size (K = 1e6, H = 20, d = 30:
7.2 GB of float32 features) fits this 24 GB machine: one copy on the workers, the files in the
page cache.
"""

from __future__ import annotations

import argparse
import logging
import time
import warnings

import numpy as np


class _Records(logging.Handler):
    def __init__(self):
        super().__init__()
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def make_arrays(K, H, d, A, seed=0):
    """``phi (K, H, d)``, ``rewards (K, H)``, ``next_phi (K, H, A, d)``: rows on the simplex,
    rewards linear in the features (seeded)."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    theta = rng.uniform(0, 1, size=(H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    return phi, rewards, next_phi


def write_disk(path, K, H, d, A, chunk=50_000, seed=0):
    """A float32 dataset directory of the arrays of :func:`make_arrays`' kind (rows on the
    simplex: normalized exponentials, i.e. Dirichlet(1); rewards linear in the features),
    written a chunk of trajectories at a time."""
    import r2pvi

    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, 1, size=(H, d))
    with r2pvi.DatasetWriter(path, horizon=H, n_features=d, n_actions=A) as w:
        for s in range(0, K, chunk):
            k = min(chunk, K - s)
            phi = rng.standard_exponential((k, H, d), dtype=np.float32)
            phi /= phi.sum(axis=-1, keepdims=True)
            nxt = rng.standard_exponential((k, H, A, d), dtype=np.float32)
            nxt /= nxt.sum(axis=-1, keepdims=True)
            w.append(phi, np.einsum("khd,hd->kh", phi, theta), nxt)


def _read_columns(path, start, stop):
    """Trajectories ``start:stop`` of a step-major ``(H, K, ...)`` file (a worker's read)."""
    return np.ascontiguousarray(np.load(path, mmap_mode="r")[:, start:stop])


def open_on_workers(path, chunk):
    """The directory's ``phi``, ``rewards``, ``next_phi`` as trajectory-major Dask arrays whose
    chunks the workers read from the files (no number passes through the client)."""
    import dask
    import dask.array as da

    out = []
    for name in ("phi", "rewards", "next_phi"):
        f = f"{path}/{name}.npy"
        stored = np.load(f, mmap_mode="r")
        n = stored.shape[1]
        parts = [da.from_delayed(dask.delayed(_read_columns)(f, s, min(n, s + chunk)),
                                 (stored.shape[0], min(n, s + chunk) - s) + stored.shape[2:],
                                 stored.dtype) for s in range(0, n, chunk)]
        out.append(da.concatenate(parts, axis=1).swapaxes(0, 1))
    return out


def timed_fit(make_ds, divergence):
    """``(wall, cpu, weights, large-graph messages)`` of one fit. The dataset is built before
    the timing (``from_features`` copies and validates the arrays; ``from_dask`` is lazy):
    what is timed is the fit, whose first use of a Dask dataset persists it on the workers,
    so persisting and scattering are part of the cost."""
    import r2pvi

    records = _Records()
    log = logging.getLogger("distributed")
    log.addHandler(records)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ds = make_ds()
            w0, c0 = time.perf_counter(), time.process_time()
            est = r2pvi.R2PVI(divergence, lam=0.5, beta=0.1).fit(ds)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        log.removeHandler(records)
    large = [m for m in records.messages + [str(w.message) for w in caught]
             if "large graph" in m.lower()]
    return wall, cpu, np.asarray(est.weights_), large


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--K", type=int, default=200_000)
    parser.add_argument("--H", type=int, default=10)
    parser.add_argument("--d", type=int, default=30)
    parser.add_argument("--A", type=int, default=2)
    parser.add_argument("--chunk", type=int, default=0,
                        help="trajectories per Dask chunk (0: K / (4 workers))")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--divergences", nargs="+", default=["kl", "tv"])
    parser.add_argument("--skip-unpersisted", action="store_true",
                        help="skip the arrays as given (the data travels with each graph)")
    parser.add_argument("--disk", default=None,
                        help="a float32 dataset directory (written if missing): the in-memory "
                             "fit opens it, the workers read their chunks of its files")
    args = parser.parse_args(argv)
    if args.disk:
        return main_disk(args)

    import dask.array as da
    from distributed import Client, LocalCluster

    import r2pvi

    K, H, d, A = args.K, args.H, args.d, args.A
    chunk = args.chunk or max(1, -(-K // (4 * args.workers)))
    phi, rewards, next_phi = make_arrays(K, H, d, A)
    print(f"K={K} H={H} d={d} A={A} chunk={chunk} workers={args.workers} "
          f"({(phi.nbytes + next_phi.nbytes + rewards.nbytes) / 2**20:.0f} MiB)")
    with LocalCluster(processes=True, n_workers=args.workers, threads_per_worker=1,
                      dashboard_address=None) as cluster, Client(cluster) as client:

        def lazy():
            return (da.from_array(phi, chunks=(chunk, H, d)),
                    da.from_array(rewards, chunks=(chunk, H)),
                    da.from_array(next_phi, chunks=(chunk, H, A, d)))

        persisted = client.persist(list(lazy()))
        client.wait_for_workers(args.workers)
        from distributed import wait

        wait(persisted)
        warm = r2pvi.OfflineDataset.from_dask(*persisted)
        r2pvi.R2PVI("tv", lam=0.5, beta=0.1).fit(warm)  # from_dask's step-major view persisted
        kinds = {"memory": lambda: r2pvi.OfflineDataset.from_features(phi, rewards, next_phi),
                 "dask persisted": lambda: r2pvi.OfflineDataset.from_dask(*persisted),
                 "dask, fitted before": lambda: warm}
        if not args.skip_unpersisted:
            kinds["dask from_array"] = lambda: r2pvi.OfflineDataset.from_dask(*lazy())
        compare(kinds, args.divergences)


def compare(kinds, divergences):
    """For each divergence, fit every kind of dataset (the first is the baseline) and print
    wall and client-CPU seconds, the ratio to the baseline, the largest weight difference
    and the large-graph warnings."""
    for div in divergences:
        res = {name: timed_fit(make, div) for name, make in kinds.items()}
        base = next(iter(res.values()))
        for name, (wall, cpu, w, large) in res.items():
            diff = float(np.max(np.abs(w - base[2])))
            print(f"{div:3s} {name:20s} wall {wall:7.2f} s  cpu {cpu:7.2f} s  "
                  f"x{wall / base[0]:6.1f}  max|dw| {diff:.1e}  "
                  f"large-graph warnings {len(large)}", flush=True)


def main_disk(args):
    """The ``--disk`` mode: fits from the files, in the client and on the workers."""
    import os

    from distributed import Client, LocalCluster

    import r2pvi

    K, H, d, A = args.K, args.H, args.d, args.A
    chunk = args.chunk or max(1, -(-K // (4 * args.workers)))
    if not os.path.isdir(args.disk):
        t0 = time.perf_counter()
        write_disk(args.disk, K, H, d, A)
        print(f"wrote {args.disk} in {time.perf_counter() - t0:.0f} s")
    ds = r2pvi.OfflineDataset.open(args.disk)
    if (ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions) != (K, H, d, A):
        raise SystemExit(f"{args.disk} holds {ds!r}, not K={K} H={H} d={d} A={A}")
    size = sum(f.stat().st_size for f in os.scandir(args.disk)) / 2**30
    print(f"K={K} H={H} d={d} A={A} chunk={chunk} workers={args.workers} "
          f"({size:.1f} GiB on disk, float32)")
    with LocalCluster(processes=True, n_workers=args.workers, threads_per_worker=1,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        client.wait_for_workers(args.workers)
        arrays = open_on_workers(args.disk, chunk)
        dask_ds = r2pvi.OfflineDataset.from_dask(*arrays)
        # The first fit of a Dask dataset persists it: the workers read the files once.
        wall, cpu, _, large = timed_fit(lambda: dask_ds, args.divergences[0])
        print(f"{args.divergences[0]:3s} dask, first fit (the workers read the files): wall "
              f"{wall:7.2f} s  cpu {cpu:7.2f} s  large-graph warnings {len(large)}", flush=True)
        timed_fit(lambda: ds, args.divergences[0])  # the files in the page cache
        compare({"memory (open)": lambda: ds, "dask (persisted)": lambda: dask_ds},
                args.divergences)


if __name__ == "__main__":
    main()
