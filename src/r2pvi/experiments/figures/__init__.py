"""The registry of reproducible figures (``r2pvi reproduce NAME``)."""

from .common import Figure, make_estimator
from .linear_mdp import FIG1A, FIG1B, FIG1C
from .put_option import FIG1D, FIG2A, FIG2B, FIG_VA
from .theory import BOUND_CHECK, RATES

FIGURES: dict[str, Figure] = {f.name: f for f in (FIG1A, FIG1B, FIG1C, FIG1D, FIG2A, FIG2B,
                                                  FIG_VA, RATES, BOUND_CHECK)}

__all__ = ["FIGURES", "Figure", "make_estimator"]
