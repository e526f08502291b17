"""Run a sweep of independent tasks serially, with joblib, or on a Dask cluster.

A sweep is a list of :class:`Task` (one setting x one replication). Task ``i`` gets the
``i``-th child of ``SeedSequence(seed).spawn(len(tasks))``, so its random numbers depend only
on the seed and its position in the sweep: results are identical whatever the backend and the
number of workers.

Every task runs with one BLAS thread by default (``blas_threads``; the environment variable
``R2PVI_BLAS_THREADS`` overrides it, 0 leaves BLAS alone): parallelism comes from processes,
one per core, not from BLAS threads competing for the same cores.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Task", "run_tasks", "spawn_seeds"]


@dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(seed_sequence, **kwargs) -> list[dict]`` (result rows).

    ``cost`` is its work relative to the sweep's other tasks (progress and time estimates only).
    """

    fn: Callable
    kwargs: dict = field(default_factory=dict)
    label: str = ""
    cost: float = 1.0


def spawn_seeds(seed: int, n: int) -> list[np.random.SeedSequence]:
    """``n`` independent child seed sequences of ``SeedSequence(seed)``."""
    return np.random.SeedSequence(seed).spawn(n)


def _call(task: Task, seq: np.random.SeedSequence, threads: int = 0) -> list[dict]:
    from .._threads import limit_blas

    with limit_blas(threads):
        return task.fn(seq, **task.kwargs)


def _check_jobs(jobs) -> int:
    if isinstance(jobs, bool) or not isinstance(jobs, int | np.integer) or not (
        jobs >= 1 or jobs == -1
    ):
        raise ValueError(f"jobs must be an integer >= 1, or -1 for one per core; got {jobs!r}")
    return (os.cpu_count() or 1) if jobs == -1 else int(jobs)


def _progress(iterable, tasks, label, enabled, cost_of=None):
    """Yield from ``iterable`` (one item per task, in task order unless ``cost_of(item)``
    gives an item's cost), reporting cost-weighted progress
    (:class:`~r2pvi.experiments.progress.SweepProgress`)."""
    from .progress import SweepProgress

    bar = SweepProgress(sum(t.cost for t in tasks), len(tasks), label, enabled)
    try:
        for i, item in enumerate(iterable):
            yield item
            bar.advance(cost_of(item) if cost_of else tasks[i].cost)
    finally:
        bar.close()


def run_tasks(
    tasks: Sequence[Task],
    *,
    seed: int = 0,
    backend: str = "serial",
    jobs: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    label: str = "sweep",
    blas_threads: int | None = None,
) -> list[dict]:
    """Run every task and return all result rows, in task order.

    Parameters
    ----------
    tasks : sequence of Task
    seed : int
        Root seed; task ``i`` receives child ``i`` of ``SeedSequence(seed)``.
    backend : {"serial", "joblib", "dask"}
        "joblib" runs ``jobs`` local processes; "dask" sends the tasks to the Dask cluster at
        ``scheduler`` (an address such as ``tcp://host:8786``) or, when ``scheduler`` is
        None, to a local ``LocalCluster`` with ``jobs`` workers.
    jobs : int
        Worker processes (joblib) or Dask workers; -1 means one per core.
    progress : bool
        Show a progress bar on standard error.
    blas_threads : int, optional
        BLAS threads of each task; None takes ``R2PVI_BLAS_THREADS`` or, when it is unset,
        1; 0 leaves BLAS alone. Needs ``threadpoolctl`` (else BLAS is left alone).

    Examples
    --------
    >>> from r2pvi.experiments.runner import Task, run_tasks
    >>> draw = lambda seq, k: [{"k": k, "x": float(np.random.default_rng(seq).random())}]
    >>> rows = run_tasks([Task(draw, {"k": k}) for k in range(3)], seed=1)
    >>> rows == run_tasks([Task(draw, {"k": k}) for k in range(3)], seed=1, backend="joblib",
    ...                   jobs=2)
    True
    """
    from .._threads import blas_threads as _threads

    jobs = _check_jobs(jobs)
    threads = _threads(1) if blas_threads is None else int(blas_threads)
    seeds = spawn_seeds(seed, len(tasks))
    if backend == "serial":
        chunks = [_call(t, s, threads) for t, s in
                  _progress(zip(tasks, seeds, strict=True), tasks, label, progress)]
    elif backend == "joblib":
        from joblib import Parallel, delayed

        parallel = Parallel(n_jobs=jobs, return_as="generator")
        gen = parallel(delayed(_call)(t, s, threads) for t, s in zip(tasks, seeds, strict=True))
        chunks = list(_progress(gen, tasks, label, progress))
    elif backend == "dask":
        chunks = _run_dask(tasks, seeds, jobs, scheduler, progress, label, threads)
    else:
        raise ValueError(f"backend must be 'serial', 'joblib' or 'dask', got {backend!r}")
    return [row for chunk in chunks for row in chunk]


def _run_dask(tasks, seeds, jobs, scheduler, progress, label, threads):
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as exc:  # pragma: no cover - exercised without the extra
        raise ImportError(
            "the Dask backend needs the 'dask' extra: pip install 'r2pvi[dask]'"
        ) from exc
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        futures = client.map(_call, tasks, seeds, [threads] * len(tasks), pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        for _ in _progress(as_completed(futures), tasks, label, progress,
                           cost_of=lambda f: tasks[index[f.key]].cost):
            pass
        return client.gather(futures)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
