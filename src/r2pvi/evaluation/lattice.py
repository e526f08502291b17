"""Exact evaluation of American put option policies on the binomial price lattice.

From an initial price ``s0`` the price at step ``h`` after ``u`` rises is
``s0 * up^u * down^(h-u)`` (the lattice recombines). For a policy that exercises at node
``(h, u)`` with probability ``e_{h,u}`` (0 or 1 for deterministic policies), the value is
the backward recursion

    V_H = 0,   V_h(u) = e_{h,u} max(0, K - s_{h,u}) + (1 - e_{h,u}) (p0 V_{h+1}(u+1)
                                                             + (1 - p0) V_{h+1}(u)).

A policy's decision at a node depends on the node's price only, so as a function of
``s0`` the decisions change only where ``s0 * c_{h,u}`` crosses a price at which the
policy switches at step ``h``. Between those points and the payoff kinks
``s0 = K / c_{h,u}``, ``V_0(s0)`` is linear in ``s0``; the expectation over a uniform
initial price is therefore a sum of trapezoids, exact once the switch prices are known.
They are located per step on a price grid (``price_resolution``) and refined by bisection
to ``~1e-14`` relative; only two switches closer together than the grid spacing could be
missed.
"""

from __future__ import annotations

import numpy as np

from .._validation import check_scalar
from ..envs.put_option import AmericanPutOption

__all__ = ["option_value", "lattice_values", "switch_prices", "decision_cuts"]


def _exercise_probability(env: AmericanPutOption, policy, h: int, prices: np.ndarray):
    """Probability of exercising at step ``h`` for each price (policies are 0/1 except
    the 'uniform' policy, 1/2)."""
    if isinstance(policy, str) and policy.lower() == "uniform":
        return np.full(prices.shape, 0.5)
    flat = prices.reshape(-1)
    return env.actions(policy, h, flat).astype(float).reshape(prices.shape)


def lattice_values(env: AmericanPutOption, s0, exercise, price_up=None) -> np.ndarray:
    """``V_0`` at initial prices ``s0 (n,)`` for exercise probabilities given per node.

    ``exercise[h]`` is an ``(n, h + 1)`` array (node ``u`` = number of rises); the
    recursion is vectorized over the n initial prices. ``price_up`` (a sequence of
    probabilities of a price rise) evaluates the same decisions under each of them at once
    and returns ``(len(price_up), n)``; None uses ``env.p0`` and returns ``(n,)``.
    """
    s0 = np.asarray(s0, dtype=float).reshape(-1)
    p = np.asarray([env.p0] if price_up is None else price_up, dtype=float)[:, None, None]
    value = np.zeros((p.shape[0], s0.size, env.H + 1))
    for h in range(env.H - 1, -1, -1):
        cont = p * value[:, :, 1 : h + 2] + (1.0 - p) * value[:, :, : h + 1]
        pay = np.maximum(0.0, env.strike - env.lattice_prices(s0, h))
        e = exercise[h]
        value = e * pay + (1.0 - e) * cont
    return value[0, :, 0] if price_up is None else value[:, :, 0]


def _decisions(env, policy, s0: np.ndarray) -> list[np.ndarray]:
    return [_exercise_probability(env, policy, h, env.lattice_prices(s0, h))
            for h in range(env.H)]


def switch_prices(env: AmericanPutOption, policy, h: int, low: float, high: float,
                  price_resolution: float = 0.01, max_bisections: int = 60,
                  subdivisions: int = 32) -> np.ndarray:
    """Prices in ``(low, high)`` where the policy's decision at step ``h`` changes.

    Found on a grid of spacing ``price_resolution`` and refined, all brackets at once, by
    splitting each bracket into ``subdivisions + 1`` parts per policy call (a bisection when
    ``subdivisions = 1``) until it is ``1e-14`` relative wide (machine precision for prices
    near 100); ``max_bisections`` bounds the work in halvings, whatever ``subdivisions``.
    """
    n = int(np.ceil((high - low) / price_resolution)) + 1
    grid = np.linspace(low, high, max(n, 2))
    dec = _exercise_probability(env, policy, h, grid)
    where = np.flatnonzero(dec[1:] != dec[:-1])
    if where.size == 0:
        return np.empty(0)
    a, b = grid[where].copy(), grid[where + 1].copy()
    da = dec[where]
    frac = np.arange(1, subdivisions + 1) / (subdivisions + 1.0)
    halvings = 0.0
    while halvings < max_bisections:
        if np.all(b - a <= 1e-14 * np.maximum(1.0, np.abs(b))):
            break
        points = a[:, None] + (b - a)[:, None] * frac[None, :]  # (brackets, subdivisions)
        dp = _exercise_probability(env, policy, h, points)
        changed = dp != da[:, None]
        # the first point past the switch (the right end when none of them is)
        first = np.where(changed.any(axis=1), changed.argmax(axis=1), subdivisions)
        rows = np.arange(a.size)
        right = np.where(first < subdivisions, points[rows, np.minimum(first, subdivisions - 1)],
                         b)
        left = np.where(first > 0, points[rows, np.maximum(first - 1, 0)], a)
        a, b = left, right
        halvings += np.log2(subdivisions + 1.0)
    return 0.5 * (a + b)


def option_value(env: AmericanPutOption, policy, s0=None, *, price_resolution: float = 0.01,
                 price_up=None):
    """Exact expected return of ``policy`` in the put option ``env``.

    Parameters
    ----------
    env : AmericanPutOption
    policy : estimator, callable ``policy(h, prices) -> actions`` or str
        ``"hold"``, ``"exercise"`` or ``"uniform"`` (exercise with probability 1/2).
    s0 : float or array, optional
        Initial price(s) at which to evaluate (returns an array for an array). None uses the
        environment's start: its fixed ``s0``, or the uniform distribution on ``s0_range``
        integrated exactly.
    price_resolution : float, default 0.01
        Spacing of the price grid that brackets the policy's switch prices.
    price_up : sequence of float, optional
        Evaluate the policy in ``env.perturbed(p)`` for every ``p`` at once and return an
        array with one value per ``p`` (a leading axis when ``s0`` is an array). The
        policy's decisions and switch prices do not depend on the probability of a price
        rise, so they are located once: much faster than one call per ``p``, and the same
        numbers.

    Returns
    -------
    float (or ndarray for an array ``s0`` or a ``price_up`` sequence)

    Examples
    --------
    >>> from r2pvi.envs import AmericanPutOption
    >>> from r2pvi.evaluation import option_value
    >>> env = AmericanPutOption()
    >>> float(option_value(env, "exercise"))      # E[max(0, 100 - U[95, 105])] = 1.25
    1.25
    >>> hold_then_exercise = lambda h, prices: (h == 1) & (prices < 100)
    >>> round(float(option_value(env, hold_then_exercise)), 10)   # closed form: 1.450080032
    1.450080032
    >>> option_value(env, hold_then_exercise, price_up=[0.5, 1.0]).round(6).tolist()
    [1.45008, 0.471078]
    """
    if not isinstance(env, AmericanPutOption):
        raise TypeError(f"env must be an AmericanPutOption, got {type(env).__name__}")
    price_resolution = check_scalar(price_resolution, "price_resolution", low=0.0,
                                    low_inclusive=False)
    if price_up is not None:
        price_up = np.asarray(price_up, dtype=float)
        if price_up.ndim != 1 or price_up.size == 0:
            raise ValueError("price_up must be a non-empty 1-D sequence of probabilities")
        for p in price_up:
            check_scalar(p, "price_up", low=0.0, high=1.0)
    if s0 is not None or env.s0 is not None:
        start = np.asarray(env.s0 if s0 is None else s0, dtype=float)
        if not np.all(np.isfinite(start)) or np.any(start <= 0):
            raise ValueError("s0 must be positive prices")
        flat = start.reshape(-1)
        values = lattice_values(env, flat, _decisions(env, policy, flat), price_up)
        if price_up is None:
            return float(values[0]) if start.ndim == 0 else values.reshape(start.shape)
        return values[:, 0] if start.ndim == 0 else values.reshape((-1, *start.shape))
    lo, hi = env.s0_range
    cuts = decision_cuts(env, policy, price_resolution)
    left, right = cuts[:-1], cuts[1:]
    exercise = _decisions(env, policy, 0.5 * (left + right))  # constant on each piece
    v_left = lattice_values(env, left, exercise, price_up)
    v_right = lattice_values(env, right, exercise, price_up)
    means = np.sum((right - left) * (v_left + v_right), axis=-1) / (2.0 * (hi - lo))
    return float(means) if price_up is None else means


def decision_cuts(env: AmericanPutOption, policy, price_resolution: float = 0.01) -> np.ndarray:
    """Sorted initial prices cutting ``s0_range`` into pieces on which every node's decision
    and every payoff's sign are constant (so ``V_0`` is linear on each piece)."""
    lo, hi = env.s0_range
    points = [np.array([lo, hi])]
    for h in range(env.H):
        c = env.lattice_prices(1.0, h)  # c_{h,u}
        points.append(env.strike / c)  # payoff kinks
        switches = switch_prices(env, policy, h, lo * c.min(), hi * c.max(), price_resolution)
        if switches.size:
            points.append((switches[:, None] / c[None, :]).reshape(-1))
    cuts = np.unique(np.concatenate(points))
    cuts = cuts[(cuts >= lo) & (cuts <= hi)]
    return cuts[np.concatenate([[True], np.diff(cuts) > 0])]
