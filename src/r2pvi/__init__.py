"""r2pvi: robust offline RL with linearly structured f-divergence regularization.

Implements R2PVI (ICML 2025) with TV, KL, chi^2 and general f-divergences, its baselines,
and exact evaluation, on one backward-induction engine.
"""

from importlib.metadata import PackageNotFoundError, version

from . import envs, evaluation, features
from .algorithms import DRPVI, DRVIL, PEVI, R2PVI, LinearEstimator
from .algorithms import load_estimator as load
from .data import OfflineDataset, SimplexFeatureWarning
from .data.storage import DatasetWriter
from .duals import FDivergence, cressie_read
from .engine.diagnostics import FitDiagnostics, StarvedFitWarning
from .engine.sizing import FeatureSizeWarning

try:
    __version__ = version("r2pvi")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "envs",
    "evaluation",
    "features",
    "OfflineDataset",
    "DatasetWriter",
    "SimplexFeatureWarning",
    "StarvedFitWarning",
    "FeatureSizeWarning",
    "FitDiagnostics",
    "FDivergence",
    "cressie_read",
    "LinearEstimator",
    "PEVI",
    "R2PVI",
    "DRPVI",
    "DRVIL",
    "load",
    "NotFittedError",
    "__version__",
]


def __getattr__(name):
    # NotFittedError derives from scikit-learn's when it is installed: built on first use so
    # that ``import r2pvi`` does not import scikit-learn.
    if name == "NotFittedError":
        from ._compat import not_fitted_error

        return not_fitted_error()
    raise AttributeError(f"module 'r2pvi' has no attribute {name!r}")
