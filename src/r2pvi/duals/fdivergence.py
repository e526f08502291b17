"""f-divergences ``D_f(mu || mu0) = E_mu0[f(dmu/dmu0)]`` with their convex conjugates.

An :class:`FDivergence` carries ``f``, its convex conjugate ``f*(s) = sup_{t>=0} s t - f(t)``
(``+inf`` outside its domain), the right end of that domain and the subdifferential of ``f``
at 1. The last two bracket the dual variable of the general dual (paper, Algorithm 1):

    inf_mu E_mu V + lam D_f(mu || mu0) = sup_alpha  alpha - lam E_mu0[f*((alpha - V)/lam)].

Conventions (the paper's): TV ``f(t) = |t-1|/2``, KL ``f(t) = t log t``,
chi^2 ``f(t) = (t-1)^2``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.special import xlogy

__all__ = [
    "FDivergence",
    "TV",
    "KL",
    "CHI2",
    "HELLINGER",
    "cressie_read",
    "get_divergence",
    "BUILTIN_DIVERGENCES",
]


@dataclass(frozen=True, eq=False)
class FDivergence:
    """An f-divergence given by ``f`` and its convex conjugate.

    Parameters
    ----------
    name : str
        Short name; built-in names are "tv", "kl", "chi2", "hellinger", "cressie_read".
    f : callable
        Vectorized ``f(t)`` for ``t >= 0``, convex, ``f(1) = 0``.
    conjugate : callable
        Vectorized ``f*(s)``; ``+inf`` where ``s`` is outside the domain.
    domain_max : float
        Right end of the domain of ``f*`` (``inf`` if unbounded). It equals
        ``lim_{t->inf} f(t)/t``: when finite, mass can move to states outside the
        nominal support, and the dual depends on the minimum value over all states.
    domain_open : bool
        Whether ``f*`` is infinite at ``domain_max`` itself.
    slope_at_one : (float, float)
        The subdifferential ``[lo, hi]`` of ``f`` at 1; the optimal dual variable lies in
        ``[V_min + lam*lo, V_max + lam*hi]``.
    params : dict
        Parameters that rebuild the divergence with :func:`get_divergence` (for saving).
    remainder : callable, optional
        Vectorized ``r(x) = f*(s0 + x) - f*(s0) - x`` at the centre ``s0`` of
        ``slope_at_one`` (``f*(s0) = s0`` and ``(f*)'(s0) = 1`` there, so ``r >= 0``), computed
        without cancellation for small ``x`` (``expm1`` and friends): the general dual is
        evaluated as ``E_i V - lam E_i[r(x)]``, exact to the values' rounding for any ``lam``.
        None forms it from ``conjugate`` (accurate for ``lam`` up to about ``1e8`` times the
        values).
    derivative : callable, optional
        Vectorized right derivative ``f'_+(t)`` (bounds the dual variable on signed ridge
        weights); None takes a right secant of ``f``.

    Examples
    --------
    >>> from r2pvi import FDivergence
    >>> import numpy as np
    >>> # chi^2 written by hand, with the paper's f(t) = (t - 1)^2
    >>> chi2 = FDivergence("my_chi2", lambda t: (t - 1.0) ** 2,
    ...                    lambda s: np.where(s >= -2, s + s * s / 4, -1.0),
    ...                    domain_max=np.inf, slope_at_one=(0.0, 0.0))
    >>> round(float(chi2.divergence([0.5, 0.5], [0.25, 0.75])), 6)
    0.333333
    """

    name: str
    f: Callable = field(repr=False)
    conjugate: Callable = field(repr=False)
    domain_max: float = np.inf
    domain_open: bool = False
    slope_at_one: tuple[float, float] = (0.0, 0.0)
    params: dict = field(default_factory=dict, compare=False)
    remainder: Callable | None = field(default=None, repr=False)
    derivative: Callable | None = field(default=None, repr=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError("name must be a non-empty string")
        if not callable(self.f) or not callable(self.conjugate):
            raise TypeError("f and conjugate must be callables (vectorized over arrays)")
        lo, hi = self.slope_at_one
        if not lo <= hi:
            raise ValueError(f"slope_at_one must be an interval lo <= hi, got {self.slope_at_one}")
        if not hi <= self.domain_max:
            raise ValueError("slope_at_one must lie in the domain of the conjugate")
        for name in ("remainder", "derivative"):
            value = getattr(self, name)
            if value is not None and not callable(value):
                raise TypeError(f"{name} must be a callable (vectorized over arrays) or None")
        # f*(s0) = s0 exactly when s0 is a subgradient of f at 1 and f(1) = 0: the general dual
        # is evaluated around that tangent (f_regularized), so a wrong slope gives wrong values
        s0 = self.centre
        with np.errstate(all="ignore"):
            at = float(np.asarray(self.conjugate(np.asarray([s0], dtype=float)))[0])
            f1 = float(np.asarray(self.f(np.asarray([1.0])))[0])
        if not (abs(f1) <= 1e-9 and abs(at - s0) <= 1e-9 * max(1.0, abs(s0))):
            raise ValueError(
                f"slope_at_one={self.slope_at_one} is not the subdifferential of f at 1 for "
                f"{self.name!r}: f(1) = {f1:g} and f*({s0:g}) = {at:g} (f(1) = 0 and "
                f"f*(s0) = s0 for s0 = f'(1) are required); pass slope_at_one=(f'(1), f'(1)) "
                "for a differentiable f (e.g. (1, 1) for KL's t log t)")

    @property
    def centre(self) -> float:
        """``s0``, the midpoint of ``slope_at_one`` (a subgradient of f at 1: ``f*(s0) = s0``)."""
        lo, hi = self.slope_at_one
        return 0.5 * (lo + hi) if np.isfinite(lo + hi) else (lo if np.isfinite(lo) else hi)

    def conjugate_remainder(self, x):
        """``f*(s0 + x) - f*(s0) - x`` (``s0`` = :attr:`centre`), the conjugate's excess over
        its tangent at ``s0``: ``>= 0``, ``O(x^2)`` for smooth f (see ``remainder``)."""
        x = np.asarray(x, dtype=float)
        if self.remainder is not None:
            return self.remainder(x)
        s0 = self.centre
        with np.errstate(over="ignore", invalid="ignore"):
            return self.conjugate(s0 + x) - self.conjugate(s0) - x

    def right_derivative(self, t, rel: float = 1e-7):
        """``f'_+(t)`` (``derivative``), or an upper bound: the right secant
        ``(f(t (1 + rel)) - f(t)) / (t rel)`` (f convex)."""
        t = np.asarray(t, dtype=float)
        if self.derivative is not None:
            return self.derivative(t)
        with np.errstate(all="ignore"):
            return (self.f(t * (1.0 + rel)) - self.f(t)) / (t * rel)

    def __eq__(self, other):
        if not isinstance(other, FDivergence):
            return NotImplemented
        if self.params and other.params:
            return self.params == other.params
        return self is other

    def __hash__(self):
        return hash(self.name)

    def __reduce__(self):
        # Built-in divergences (params set) pickle by their parameters, not their functions
        # (lambdas and closures cannot be pickled); custom ones pickle field by field.
        if self.params:
            return (get_divergence, (dict(self.params),))
        return super().__reduce__()

    def divergence(self, mu, mu0) -> float:
        """``D_f(mu || mu0)`` for finite distributions (``+inf`` when not absolutely continuous,
        unless ``f`` grows linearly, in which case mass off the support costs ``domain_max``)."""
        mu = np.asarray(mu, dtype=float)
        mu0 = np.asarray(mu0, dtype=float)
        on = mu0 > 0
        value = float(np.sum(mu0[on] * self.f(mu[on] / mu0[on])))
        off = float(mu[~on].sum())
        if off > 0:
            value = value + off * self.domain_max if np.isfinite(self.domain_max) else np.inf
        return value


def _kl_remainder(x):
    """``e^x - 1 - x`` (KL at s0 = 1); absolute error ~ 2^-53 |x|."""
    with np.errstate(over="ignore"):
        return np.expm1(x) - x


def _chi2_remainder(x):
    """``f*(x) - x`` (chi^2 at s0 = 0): ``x^2 / 4`` for ``x >= -2``, ``-1 - x`` below."""
    return np.where(x >= -2.0, 0.25 * x * x, -1.0 - x)


def _hellinger_remainder(x):
    """``x / (1 - x) - x = x^2 / (1 - x)`` for ``x < 1`` (Hellinger at s0 = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(x < 1.0, x * x / (1.0 - x), np.inf)


def _tv_remainder(x):
    """``max(x, -1/2) - x`` for ``x <= 1/2`` (TV at s0 = 0), ``+inf`` above."""
    return np.where(x <= 0.5, np.maximum(-0.5 - x, 0.0), np.inf)


def _tv_conjugate(s):
    s = np.asarray(s, dtype=float)
    return np.where(s <= 0.5, np.maximum(s, -0.5), np.inf)


def _kl_conjugate(s):
    return np.exp(np.asarray(s, dtype=float) - 1.0)


def _chi2_conjugate(s):
    s = np.asarray(s, dtype=float)
    return np.where(s >= -2.0, s + 0.25 * s * s, -1.0)


def _hellinger_conjugate(s):
    s = np.asarray(s, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(s < 1.0, s / (1.0 - s), np.inf)


TV = FDivergence(
    "tv",
    lambda t: 0.5 * np.abs(np.asarray(t, dtype=float) - 1.0),
    _tv_conjugate,
    domain_max=0.5,
    slope_at_one=(-0.5, 0.5),
    params={"name": "tv"},
    remainder=_tv_remainder,
    derivative=lambda t: np.where(np.asarray(t, dtype=float) >= 1.0, 0.5, -0.5),
)
KL = FDivergence(
    "kl",
    lambda t: xlogy(t, t),
    _kl_conjugate,
    slope_at_one=(1.0, 1.0),
    params={"name": "kl"},
    remainder=_kl_remainder,
    derivative=lambda t: np.log(np.asarray(t, dtype=float)) + 1.0,
)
CHI2 = FDivergence(
    "chi2",
    lambda t: (np.asarray(t, dtype=float) - 1.0) ** 2,
    _chi2_conjugate,
    slope_at_one=(0.0, 0.0),
    params={"name": "chi2"},
    remainder=_chi2_remainder,
    derivative=lambda t: 2.0 * (np.asarray(t, dtype=float) - 1.0),
)
HELLINGER = FDivergence(
    "hellinger",
    lambda t: (np.sqrt(np.asarray(t, dtype=float)) - 1.0) ** 2,
    _hellinger_conjugate,
    domain_max=1.0,
    domain_open=True,
    slope_at_one=(0.0, 0.0),
    params={"name": "hellinger"},
    remainder=_hellinger_remainder,
    derivative=lambda t: 1.0 - 1.0 / np.sqrt(np.asarray(t, dtype=float)),
)


def cressie_read(k: float) -> FDivergence:
    """The Cressie-Read family ``f_k(t) = (t^k - k t + k - 1) / (k (k - 1))``, k not in {0, 1}.

    ``k = 2`` is half the chi^2 divergence, ``k = 1/2`` twice the squared Hellinger distance;
    ``k -> 1`` tends to KL. The conjugate is
    ``f_k*(s) = ((1 + (k-1) s)_+^{k/(k-1)} - 1) / k`` (domain ``s < 1/(1-k)`` when ``k < 1``).

    Examples
    --------
    >>> from r2pvi.duals import cressie_read
    >>> d = cressie_read(2.0)
    >>> float(d.f(3.0)), float(d.conjugate(1.0))
    (2.0, 1.5)
    """
    if isinstance(k, bool) or not isinstance(k, int | float | np.floating | np.integer):
        raise TypeError(f"k must be a real number, got {k!r}")
    k = float(k)
    if not np.isfinite(k) or k in (0.0, 1.0):
        raise ValueError(f"k must be finite and not 0 or 1 (use 'kl' for k -> 1), got {k}")

    def f(t):
        t = np.asarray(t, dtype=float)
        with np.errstate(divide="ignore"):
            return (np.power(t, k) - k * t + k - 1.0) / (k * (k - 1.0))

    def conjugate(s):
        s = np.asarray(s, dtype=float)
        base = 1.0 + (k - 1.0) * s
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if k > 1.0:
                return (np.power(np.maximum(base, 0.0), k / (k - 1.0)) - 1.0) / k
            return np.where(base > 0, (np.power(np.where(base > 0, base, 1.0), k / (k - 1.0))
                                       - 1.0) / k, np.inf)

    def remainder(x):
        # f*(x) - x at s0 = 0: expm1(k/(k-1) log1p((k-1) x)) / k - x (no cancellation in f*)
        x = np.asarray(x, dtype=float)
        q = (k - 1.0) * x
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            inside = np.expm1(k / (k - 1.0) * np.log1p(np.where(q > -1.0, q, 0.0))) / k - x
            return np.where(q > -1.0, inside, -1.0 / k - x if k > 1.0 else np.inf)

    def derivative(t):
        t = np.asarray(t, dtype=float)
        with np.errstate(divide="ignore"):
            return (np.power(t, k - 1.0) - 1.0) / (k - 1.0)

    domain_max = np.inf if k > 1.0 else 1.0 / (1.0 - k)
    return FDivergence(
        f"cressie_read({k:g})",
        f,
        conjugate,
        domain_max=domain_max,
        domain_open=k < 1.0,
        slope_at_one=(0.0, 0.0),
        params={"name": "cressie_read", "k": k},
        remainder=remainder,
        derivative=derivative,
    )


BUILTIN_DIVERGENCES = {"tv": TV, "kl": KL, "chi2": CHI2, "hellinger": HELLINGER}


def get_divergence(spec) -> FDivergence:
    """Resolve a divergence name, parameter dict (as in ``FDivergence.params``) or object."""
    if isinstance(spec, FDivergence):
        return spec
    if isinstance(spec, str):
        key = spec.lower().replace("-", "").replace("_", "").replace("^", "")
        aliases = {"tv": "tv", "kl": "kl", "chi2": "chi2", "chisquare": "chi2",
                   "hellinger": "hellinger", "squaredhellinger": "hellinger"}
        if key in aliases:
            return BUILTIN_DIVERGENCES[aliases[key]]
        raise ValueError(
            f"unknown divergence {spec!r}: use 'tv', 'kl', 'chi2', 'hellinger', "
            "cressie_read(k) or an FDivergence"
        )
    if isinstance(spec, dict) and spec.get("name") == "cressie_read":
        return cressie_read(spec["k"])
    if isinstance(spec, dict) and spec.get("name") in BUILTIN_DIVERGENCES:
        return BUILTIN_DIVERGENCES[spec["name"]]
    raise TypeError(
        f"divergence must be a name ('tv', 'kl', 'chi2', ...) or an FDivergence, got {spec!r}"
    )
