"""The duals of the paper, written once against a linear expectation operator."""

from .constrained import chi2_constrained, kl_constrained, tv_constrained
from .fdivergence import (
    BUILTIN_DIVERGENCES,
    CHI2,
    HELLINGER,
    KL,
    TV,
    FDivergence,
    cressie_read,
    get_divergence,
)
from .general_f import f_regularized
from .gram import GramFactor, GramMatrixError, cholesky_gram, choose_form
from .operator import ExpectationOperator, FactorExpectation, RidgeExpectation
from .regularized import chi2_regularized, kl_regularized, tv_regularized
from .sorting import TruncationCumulants

__all__ = [
    "BUILTIN_DIVERGENCES",
    "CHI2",
    "HELLINGER",
    "KL",
    "TV",
    "FDivergence",
    "cressie_read",
    "get_divergence",
    "ExpectationOperator",
    "FactorExpectation",
    "RidgeExpectation",
    "TruncationCumulants",
    "GramFactor",
    "GramMatrixError",
    "choose_form",
    "cholesky_gram",
    "chi2_regularized",
    "f_regularized",
    "kl_regularized",
    "tv_regularized",
    "tv_constrained",
    "kl_constrained",
    "chi2_constrained",
]
