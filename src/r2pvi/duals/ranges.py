"""The range every factor value of a step must lie in, and the projection onto it.

Each factor value ``w_{h,i}`` estimates a (robust) expectation of ``V_{h+1}`` under a
distribution, so the truth lies in the range of ``V_{h+1}``: ``[0, (H - h - 1) r_max]`` (the
engine clips ``Q_{h+1}`` to it; known values widen it) and, for an uncertainty ball or a
regularized problem, at most the plain expectation (``mu0`` is feasible). A ridge
estimate has signed weights and can leave that range; projecting it back onto an interval
that contains the truth never increases its error (``|P(x) - t| <= |x - t|`` for ``t`` in
the interval). Every step rule ends with :func:`project_onto_range`, so that

    lower <= w_{h,i} <= min(upper, plain_i)      (plain only for the rules that pass it).

The rules compute the interval with :func:`value_range` from the step's values ``v`` and the
step's own bound ``StepContext.next_value_bound = (H - h - 1) r_max``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["value_range", "value_extent", "project_onto_range", "clip", "value_unit"]


def value_unit(extent: tuple[float, float]) -> float:
    """The largest power of two at most ``max(|min v|, |max v|)`` (``extent = (min v, max
    v)``; 1 when every value is 0): the unit the step rules whose formulas square values
    (chi^2) or compare them with absolute tolerances (general f, the KL ball's search) work
    in. The values divided by it lie in ``[-2, 2]``, so no square overflows or underflows
    for any finite values, and the formulas see the same numbers whatever the scale of the
    rewards and ``r_max``; dividing and multiplying by a power of two is exact.

    Examples
    --------
    >>> value_unit((0.0, 1.0)), value_unit((0.0, 3.0)), value_unit((-0.3, 0.1))
    (1.0, 2.0, 0.25)
    >>> value_unit((0.0, 0.0))
    1.0
    """
    top = max(abs(float(extent[0])), abs(float(extent[1])))
    if not (top > 0.0 and math.isfinite(top)):
        return 1.0
    return math.ldexp(1.0, math.frexp(top)[1] - 1)


def value_extent(v: np.ndarray) -> tuple[float, float]:
    """``(min v, max v)`` as floats: computed once per step by the rules and handed to
    :func:`value_range` and the duals that need them (each is a pass over the K values).

    Examples
    --------
    >>> import numpy as np
    >>> value_extent(np.array([0.5, 2.0, 1.0]))
    (0.5, 2.0)
    """
    v = np.asarray(v, dtype=float)
    return float(np.min(v)), float(np.max(v))


def value_range(v: np.ndarray, upper: float, lower: float = 0.0, *,
                extent: tuple[float, float] | None = None) -> tuple[float, float]:
    """``(lower, upper)``: the known range of the next-step values.

    ``lower`` defaults to 0, where the engine clips ``Q_{h+1}`` (pass a smaller known lower
    bound if values can be negative); ``upper`` is the step's bound ``(H - h - 1) r_max``.
    Each is widened to ``min(v)`` / ``max(v)`` if known values (absorbing states, stopping
    payoffs) lie outside it. ``extent``: ``(min v, max v)`` when already known
    (:func:`value_extent`), to save the two passes over ``v``.

    Examples
    --------
    >>> import numpy as np
    >>> value_range(np.array([0.5, 2.0]), upper=3.0)
    (0.0, 3.0)
    >>> value_range(np.array([-0.5, 2.0]), upper=1.0)
    (-0.5, 2.0)
    """
    v_lo, v_hi = value_extent(v) if extent is None else extent
    return min(float(lower), v_lo), max(float(upper), v_hi)


def clip(x, lower, upper, out=None) -> np.ndarray:
    """``np.clip(x, lower, upper, out=out)``: ``min(max(x, lower), upper)`` with NaN kept, as
    two ufunc calls without np.clip's Python layers (a few microseconds a call, which the
    duals' many d-sized clips per step add up)."""
    out = np.maximum(x, lower, out=out)
    return np.minimum(out, upper, out=out)


def project_onto_range(w: np.ndarray, lower: float, upper: float, plain=None) -> np.ndarray:
    """``clip(w, lower, min(upper, plain))``: factor values projected onto their known range.

    ``plain (d,)``, optional, is the plain (non-robust) estimate of the same step, an upper
    bound for every robust value (the nominal distribution is in every uncertainty set); it is
    itself first projected onto ``[lower, upper]``. Infinite entries of ``w`` go to the bound
    on their side; NaN is not hidden (it stays NaN, so that tests see it).

    Examples
    --------
    >>> import numpy as np
    >>> project_onto_range(np.array([-1.0, 0.5, np.inf]), 0.0, 2.0)
    array([0. , 0.5, 2. ])
    >>> project_onto_range(np.array([1.5, 0.5]), 0.0, 2.0, plain=np.array([1.0, 3.0]))
    array([1. , 0.5])
    """
    w = np.asarray(w, dtype=float)
    if plain is None:
        return clip(w, lower, upper)
    top = np.clip(np.asarray(plain, dtype=float), lower, upper)
    return np.minimum(np.maximum(w, lower), top)
