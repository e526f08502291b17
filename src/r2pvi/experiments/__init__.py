"""Experiments: figure configurations, the sweep runner, result files and plots."""

from .reproduce import figure_names, reproduce_figure
from .runner import Task, run_tasks

__all__ = ["reproduce_figure", "figure_names", "Task", "run_tasks"]
