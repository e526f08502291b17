"""Whether a feature map's dimension fits the data: ``d`` against the transitions of one
regression, read from a fit's :class:`~r2pvi.engine.diagnostics.FitDiagnostics` (no
other read of the data)."""

from __future__ import annotations

import warnings

import numpy as np

from .diagnostics import FitDiagnostics
from .steps import pooled_steps

__all__ = ["FeatureSizeWarning", "oversized", "warn_if_oversized"]


class FeatureSizeWarning(UserWarning):
    """A feature map with more features ``d`` than the transitions of one regression
    (per-step form: the largest step; pooled form: every transition): the ridge
    regressions are underdetermined and the fit costs time for nothing. See
    docs/your-own-task.md, "Sizing a feature map"."""


def _rows(report: FitDiagnostics, n_trajectories: int) -> tuple[int, bool]:
    """The transitions of the largest regression, and whether they were counted (False: an
    upper bound from the dataset's shape, ``K`` per step or ``K (H - 1)`` pooled: the last
    step's next states are not data)."""
    if report.rows is not None and report.rows.size:
        return int(np.max(report.rows)), True
    bound = n_trajectories * (pooled_steps(report.horizon) if report.pooled else 1)
    return bound, False


def oversized(report: FitDiagnostics | None, n_features: int,
              n_trajectories: int) -> str | None:
    """The warning's message when ``n_features`` exceeds the transitions of every
    regression of the fit, else None."""
    if report is None:
        return None
    rows, counted = _rows(report, n_trajectories)
    if n_features <= rows:
        return None
    if report.pooled:
        where = f"the pooled regression holds {rows} transitions"
        fix = ""
    else:
        where = (f"the largest of the {report.horizon} per-step regressions holds {rows} "
                 "transitions")
        fix = ("pool the steps of a stationary task (time_homogeneous=True: "
               f"up to {n_trajectories * pooled_steps(report.horizon)} rows in one regression), ")
    if not counted:
        where += " at most"
    return (
        f"the feature map has d = {n_features} features but {where}: d is "
        f"{n_features / max(rows, 1):.3g} "
        "times the rows, so each regression is underdetermined and rests on the ridge. Fix: "
        + fix + "use a smaller map (fewer tiles or tilings, fewer RBF centers, or "
        "r2pvi.features.StateAggregation with fewer bins: d = cells x n_actions), or collect "
        "more episodes. See docs/your-own-task.md, 'Sizing a feature map'.")


def warn_if_oversized(report: FitDiagnostics | None, n_features: int, n_trajectories: int,
                      stacklevel: int = 3) -> None:
    """Warn (:class:`FeatureSizeWarning`) when :func:`oversized` gives a message."""
    message = oversized(report, n_features, n_trajectories)
    if message is not None:
        warnings.warn(message, FeatureSizeWarning, stacklevel=stacklevel)
