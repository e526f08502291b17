"""The paper's theoretical constants: beta of the instance-dependent bound and the corollary.

Formulas as written in the paper (Section 5): Theorem "instance-dependent upper bounds"
(gamma = 1, penalty ``beta sum_i ||phi_i 1_i||_{Lambda_h^{-1}}``) and its corollary under the
robust regularized partial coverage assumption with constant ``c_dagger``.
"""

from __future__ import annotations

import math

from .._validation import check_scalar

__all__ = ["theoretical_beta", "xi", "instance_dependent_bound", "instance_independent_bound"]

_DIVERGENCES = ("tv", "kl", "chi2")


def _check(divergence, d, H, K, lam, delta):
    if divergence not in _DIVERGENCES:
        raise ValueError(f"divergence must be one of {_DIVERGENCES} (the theorem covers these), "
                         f"got {divergence!r}")
    d = check_scalar(d, "d", low=1, integer=True)
    H = check_scalar(H, "H", low=1, integer=True)
    K = check_scalar(K, "K", low=1, integer=True)
    lam = check_scalar(lam, "lam", low=0.0, low_inclusive=False)
    delta = check_scalar(delta, "delta", low=0.0, high=1.0, low_inclusive=False)
    if delta >= 1.0:
        raise ValueError(f"delta must be in (0, 1), got {delta}")
    return d, H, K, lam, delta


def xi(divergence: str, d: int, H: int, K: int, lam: float, delta: float) -> float:
    """The log factor of the theorem: ``xi_TV = 2 log(1024 H d^{1/2} K^2 / delta)``,
    ``xi_KL = log(1024 d lam^2 K^3 H / delta)``,
    ``xi_chi2 = log(192 K^5 H^6 d^3 (1 + H/(2 lam))^3 / delta)``."""
    d, H, K, lam, delta = _check(divergence, d, H, K, lam, delta)
    if divergence == "tv":
        return 2.0 * (math.log(1024 * H * math.sqrt(d)) + 2 * math.log(K) - math.log(delta))
    if divergence == "kl":
        return (math.log(1024 * d * H) + 2 * math.log(lam) + 3 * math.log(K)
                - math.log(delta))
    return (math.log(192) + 5 * math.log(K) + 6 * math.log(H) + 3 * math.log(d)
            + 3 * math.log1p(H / (2 * lam)) - math.log(delta))


def theoretical_beta(divergence: str, d: int, H: int, K: int, lam: float,
                     delta: float = 0.05) -> float:
    """beta of the instance-dependent upper-bound theorem.

    ``TV: 16 H d sqrt(xi_TV)``; ``KL: 16 d lam e^{H/lam} sqrt(H/lam + xi_KL)``;
    ``chi^2: 8 d H (1 + 3H/(4 lam)) sqrt(xi_chi2)``. The KL value overflows to ``inf`` for
    small ``lam`` (``e^{H/lam}``): that is the theorem's constant, returned as is.

    Examples
    --------
    >>> from r2pvi.theory import theoretical_beta
    >>> round(theoretical_beta("tv", d=4, H=3, K=100, lam=1.0, delta=0.05), 1)
    1242.2
    """
    d, H, K, lam, delta = _check(divergence, d, H, K, lam, delta)
    x = xi(divergence, d, H, K, lam, delta)
    if divergence == "tv":
        return 16.0 * H * d * math.sqrt(x)
    if divergence == "kl":
        if H / lam > 700.0:
            return math.inf
        return 16.0 * d * lam * math.exp(H / lam) * math.sqrt(H / lam + x)
    return 8.0 * d * H * (1.0 + 3.0 * H / (4.0 * lam)) * math.sqrt(x)


def instance_dependent_bound(divergence: str, d: int, H: int, K: int, lam: float,
                             delta: float, term: float) -> float:
    """The theorem's bound ``2 beta * term`` on ``SubOpt(pi_hat, s, lam)``.

    Paper, Thm. instance-dependent upper bounds; ``beta`` from :func:`theoretical_beta` and
    ``term`` the uncertainty term (:func:`r2pvi.theory.uncertainty_term`) at the same ``s``.

    Examples
    --------
    >>> from r2pvi.theory import instance_dependent_bound, theoretical_beta
    >>> b = instance_dependent_bound("chi2", d=4, H=3, K=100, lam=1.0, delta=0.05, term=0.1)
    >>> b == 2 * theoretical_beta("chi2", 4, 3, 100, 1.0, 0.05) * 0.1
    True
    """
    t = check_scalar(term, "term", low=0.0)
    return 2.0 * theoretical_beta(divergence, d, H, K, lam, delta) * t


def instance_independent_bound(divergence: str, d: int, H: int, K: int, lam: float,
                               delta: float, c_dagger: float) -> float:
    """The corollary's bound ``beta d H / sqrt(c_dagger K)`` on SubOpt (as the paper states it:
    TV ``16 H^2 d^2 sqrt(xi_TV) / sqrt(c K)``, and likewise for KL and chi^2)."""
    c = check_scalar(c_dagger, "c_dagger", low=0.0, low_inclusive=False)
    beta = theoretical_beta(divergence, d, H, K, lam, delta)
    return beta * d * H / math.sqrt(c * K)
