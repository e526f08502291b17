"""Estimators: thin objects that tell the engine how to turn next-step values into weights."""

from ._score import Scorer
from .base import ESTIMATOR_REGISTRY, LinearEstimator, load_estimator
from .drpvi import DRPVI, TVBallRule
from .drvil import DRVIL, KLBallRule
from .pevi import PEVI, RidgeRule
from .r2pvi import R2PVI, Chi2Rule, FDivergenceRule, KLRule, TVRule

__all__ = [
    "ESTIMATOR_REGISTRY",
    "LinearEstimator",
    "Scorer",
    "load_estimator",
    "PEVI",
    "R2PVI",
    "RidgeRule",
    "TVRule",
    "KLRule",
    "Chi2Rule",
    "FDivergenceRule",
    "DRPVI",
    "DRVIL",
    "TVBallRule",
    "KLBallRule",
]
