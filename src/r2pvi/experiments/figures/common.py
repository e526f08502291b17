"""What every figure shares: the figure spec, estimator construction, evaluation, plotting."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ...algorithms import PEVI, R2PVI
from ..plotting import line_panels
from ..results import summarize
from ..runner import Task

__all__ = ["Figure", "make_estimator", "evaluate", "series_panels", "spread_note",
           "ALGORITHM_KINDS"]


@dataclass
class Figure:
    """A reproducible figure: default settings, the sweep's tasks, the plot and the table.

    ``tasks(settings) -> list[Task]``; ``plot(rows, settings) -> matplotlib figure``;
    ``table(rows, settings) -> str``. ``serial`` figures (timings) always run in one process.
    ``quantity`` and ``unit`` say what the rows' ``value`` column holds (written to the CSV).
    ``plot_cost`` is the time to draw and save the plot relative to a simple one (the order
    in which ``r2pvi reproduce all`` hands plots to its processes).
    """

    name: str
    claim: str
    defaults: dict
    tasks: Callable[[dict], list[Task]]
    plot: Callable
    table: Callable
    serial: bool = False
    notes: list[str] = field(default_factory=list)
    quantity: str = "average return"
    unit: str = "return"
    plot_cost: float = 1.0


ALGORITHM_KINDS = ("PEVI", "R2PVI", "DRPVI", "DRVI-L", "VA-DRPVI", "VA-R2PVI-TV")


def make_estimator(kind: str, param=None, *, divergence="tv", **common):
    """Build an estimator by kind: ``"PEVI"``, ``"R2PVI"`` (``param`` = lam, with
    ``divergence``), ``"DRPVI"`` / ``"DRVI-L"`` (``param`` = rho), ``"VA-DRPVI"``,
    ``"VA-R2PVI-TV"``. ``common`` holds beta, gamma, reward_weights, r_max, ..."""
    from ...algorithms import DRPVI, DRVIL

    if kind == "PEVI":
        return PEVI(**common)
    if kind == "R2PVI":
        return R2PVI(divergence, param, **common)
    if kind == "VA-R2PVI-TV":
        return R2PVI("tv", param, variance_aware=True, **common)
    if kind == "DRPVI":
        return DRPVI(param, **common)
    if kind == "VA-DRPVI":
        return DRPVI(param, variance_aware=True, **common)
    if kind == "DRVI-L":
        return DRVIL(param, **common)
    raise ValueError(f"unknown algorithm kind {kind!r}; use one of {ALGORITHM_KINDS}")


def evaluate(env, policy, evaluation: str, test_episodes: int, rng) -> float:
    """Exact expected return, or the mean of ``test_episodes`` Monte Carlo episodes (the
    paper's protocol) when ``evaluation == "mc"``."""
    from ...evaluation import expected_return, monte_carlo_return

    if evaluation == "exact":
        return float(expected_return(env, policy))
    if evaluation == "mc":
        return float(monte_carlo_return(env, policy, test_episodes, seed=rng)[0])
    raise ValueError(f"evaluation must be 'exact' or 'mc', got {evaluation!r}")


def series_panels(rows, panel_key, series_key, x_key, panel_fmt="{}", series_fmt="{}"):
    """Group rows into ``[(panel title, {series: (x, mean, std)})]`` for :func:`line_panels`.

    ``std`` is the sample standard deviation over the rows of a point, None for a series
    whose points each come from one row (an exact value, one replication: no spread).
    """
    summary = summarize(rows, [panel_key, series_key, x_key])
    panels: dict = {}
    for s in summary:
        panel = panels.setdefault(panel_fmt.format(s[panel_key]), {})
        x, m, sd = panel.setdefault(series_fmt.format(s[series_key]), ([], [], []))
        x.append(s[x_key])
        m.append(s["mean"])
        sd.append(s["std"] if s["n"] > 1 else None)
    out = []
    for title, series in panels.items():
        ordered = {}
        for label, (x, m, sd) in series.items():
            order = np.argsort(x)
            spread = None if any(v is None for v in sd) else [sd[i] for i in order]
            ordered[label] = ([x[i] for i in order], [m[i] for i in order], spread)
        out.append((title, ordered))
    return out


def spread_note(n: int, what: str = "replications", kind: str = "bands") -> str:
    """The legend title saying what the bands or bars are: ``+-1 s.d. over n replications``.

    Every figure shows the sample standard deviation (the spread of one run), never the
    standard error of the mean.
    """
    return f"{kind}: ±1 standard deviation over {n} {what}"


def plot_series(rows, panel_key, series_key, x_key, *, xlabel, ylabel, title, **kw):
    """Convenience: :func:`series_panels` then :func:`line_panels`."""
    fmt = {k: kw.pop(k) for k in ("panel_fmt", "series_fmt") if k in kw}
    return line_panels(series_panels(rows, panel_key, series_key, x_key, **fmt),
                       xlabel=xlabel, ylabel=ylabel, title=title, **kw)
