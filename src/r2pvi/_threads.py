"""How many BLAS threads a fit and a sweep use (``R2PVI_BLAS_THREADS``).

r2pvi's fits are many small dense products (d x d Gram matrices, K x d by d x A products),
for which a multi-threaded BLAS spends more time waking and synchronising its threads than
computing, and on a busy machine its threads fight the other processes for the cores
(``benchmarks/bench_threads.py`` measures it). So, when ``threadpoolctl`` is installed
(the ``experiments`` extra):

- each ``fit`` runs with at most :data:`DEFAULT_FIT_THREADS` BLAS thread(s);
- a sweep (``r2pvi reproduce``, :func:`r2pvi.experiments.runner.run_tasks`) runs one
  process per core with one BLAS thread each.

Set the environment variable ``R2PVI_BLAS_THREADS`` to a positive integer to use that many
threads instead, or to ``0`` to leave BLAS alone (r2pvi then never changes the thread
count; use ``threadpoolctl.threadpool_limits`` yourself). Without ``threadpoolctl`` BLAS is
left alone.
"""

from __future__ import annotations

import contextlib
import os

__all__ = ["ENV_VAR", "DEFAULT_FIT_THREADS", "blas_threads", "limit_blas"]

ENV_VAR = "R2PVI_BLAS_THREADS"
#: BLAS threads of a single fit when ``R2PVI_BLAS_THREADS`` is unset (measured: see above).
DEFAULT_FIT_THREADS = 1

_CONTROLLER = None


def _env_threads() -> int | None:
    """``R2PVI_BLAS_THREADS`` as an int >= 0, None when unset or empty."""
    raw = os.environ.get(ENV_VAR, "").strip()
    if not raw:
        return None
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if value < 0:
        raise ValueError(
            f"environment variable {ENV_VAR} must be an integer >= 0 (0 = leave BLAS alone), "
            f"got {raw!r}"
        )
    return value


def blas_threads(default: int = DEFAULT_FIT_THREADS) -> int:
    """The BLAS thread count r2pvi uses: ``R2PVI_BLAS_THREADS`` if set, else ``default``
    (0 means: leave BLAS alone)."""
    env = _env_threads()
    return default if env is None else env


def _controller():
    global _CONTROLLER
    if _CONTROLLER is None:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:
            _CONTROLLER = False
        else:
            _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


def limit_blas(threads: int | None = None):
    """A context manager running its block with at most ``threads`` BLAS threads.

    ``threads=None`` takes :func:`blas_threads`; 0, or no ``threadpoolctl``, does nothing.
    """
    n = blas_threads() if threads is None else threads
    ctl = _controller() if n > 0 else False
    if not ctl:
        return contextlib.nullcontext()
    return ctl.limit(limits=n, user_api="blas")
