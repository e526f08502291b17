"""Run one figure end to end: settings, sweep, result files, plot, terminal summary."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from .config import check_settings, merge_settings
from .figures import FIGURES, IN_ALL
from .results import write_results
from .runner import run_tasks

__all__ = ["reproduce_figure", "figure_names", "draw_plots"]


def figure_names(*, benchmarks: bool = False) -> list[str]:
    """Names that ``r2pvi reproduce all`` runs (the paper's); with ``benchmarks``, every
    name ``r2pvi reproduce`` accepts (``cartpole`` and ``mountaincar`` run by name only)."""
    return list(FIGURES) if benchmarks else list(IN_ALL)


def reproduce_figure(name: str, out_dir, *, toml=None, overrides=None, seed: int = 0,
                     backend: str = "serial", jobs: int = 1, scheduler=None,
                     progress: bool = True, plot: bool = True, stream=None) -> dict:
    """Reproduce figure ``name`` into ``out_dir``; returns its rows, settings and file paths.

    Writes ``NAME.csv``, ``NAME.json`` (rows with configuration and library version),
    ``NAME.png`` and ``NAME.pdf``, and prints the summary table to ``stream``.
    """
    if name not in FIGURES:
        raise ValueError(f"unknown figure {name!r}; choose from {', '.join(FIGURES)} or 'all'")
    fig = FIGURES[name]
    stream = stream or sys.stdout
    settings = check_settings(name, merge_settings(name, fig.defaults, toml, overrides))
    tasks = fig.tasks(settings)
    if fig.serial and backend != "serial":
        print(f"[{name}] timings run serially in one process (ignoring the {backend} backend)",
              file=stream)
        backend = "serial"
    t0 = time.perf_counter()
    rows = run_tasks(tasks, seed=seed, backend=backend, jobs=jobs, scheduler=scheduler,
                     progress=progress, label=name)
    elapsed = time.perf_counter() - t0
    config = {"settings": settings, "seed": seed, "backend": backend, "jobs": jobs,
              "claim": fig.claim}
    paths = write_results(rows, out_dir, name, config, quantity=fig.quantity,
                          unit=fig.unit)
    if plot:
        paths.update(_draw(name, rows, settings, out_dir))
    print(f"\n== {name}: {fig.claim}", file=stream)
    print(fig.table(rows, settings), file=stream)
    print(f"({len(tasks)} tasks, {elapsed:.1f} s; files in {Path(out_dir)})", file=stream)
    return {"rows": rows, "settings": settings, "paths": paths, "seconds": elapsed}


def _draw(name: str, rows: list[dict], settings: dict, out_dir) -> dict[str, Path]:
    """Draw figure ``name`` from its rows and save ``NAME.png`` and ``NAME.pdf``."""
    from .plotting import save_figure

    return save_figure(FIGURES[name].plot(rows, settings), out_dir, name)


def draw_plots(results, out_dir, *, jobs: int = 1) -> dict[str, dict[str, Path]]:
    """Draw and save the plots of finished sweeps, ``jobs`` at a time in worker processes.

    ``results`` is a sequence of ``(name, rows, settings)`` (the ``rows`` and ``settings``
    that :func:`reproduce_figure` returns); ``r2pvi reproduce all`` draws its nine plots this
    way, after the sweeps, in parallel (joblib) rather than one after another between them.
    Returns ``{name: {"png": path, "pdf": path}}``.
    """
    results = list(results)
    if jobs > 1 and len(results) > 1:
        from joblib import Parallel, delayed

        # the costliest plots first, so that no process is left with a long one at the end
        order = sorted(range(len(results)), key=lambda i: -FIGURES[results[i][0]].plot_cost)
        drawn = Parallel(n_jobs=min(jobs, len(results)), batch_size=1)(
            delayed(_draw)(*results[i], out_dir) for i in order)
        paths = dict(zip(order, drawn, strict=True))
        return {results[i][0]: paths[i] for i in range(len(results))}
    return {name: _draw(name, rows, settings, out_dir) for name, rows, settings in results}
