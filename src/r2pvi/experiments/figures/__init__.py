"""The registry of reproducible figures (``r2pvi reproduce NAME``)."""

from .cartpole_protocol import CARTPOLE
from .classic_control import MOUNTAINCAR
from .common import Figure, make_estimator
from .linear_mdp import FIG1A, FIG1B, FIG1C
from .put_option import FIG1D, FIG2A, FIG2B, FIG_VA
from .theory import BOUND_CHECK, RATES

FIGURES: dict[str, Figure] = {f.name: f for f in (FIG1A, FIG1B, FIG1C, FIG1D, FIG2A, FIG2B,
                                                  FIG_VA, RATES, BOUND_CHECK)}
# Benchmarks beyond the paper: run by name, not part of `reproduce all`.
BENCHMARKS: dict[str, Figure] = {f.name: f for f in (CARTPOLE, MOUNTAINCAR)}
IN_ALL = list(FIGURES)
FIGURES.update(BENCHMARKS)

__all__ = ["FIGURES", "BENCHMARKS", "IN_ALL", "Figure", "make_estimator"]
