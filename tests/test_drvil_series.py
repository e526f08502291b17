"""DRVI-L's fast paths (``kl_constrained``, benchmarks/bench_fit.py) against their reference forms.

The Newton steps of the KL-ball dual evaluate each factor at its own ``b`` from Taylor moments
kept at a few shared nodes (``_series_*``) instead of ``n`` exponentials per factor; the
reference is the exact per-factor evaluation (``_per_factor_exact``) and, end to end, the
solver with the series switched off (the local grid of exact evaluations, as before).
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.duals import FactorExpectation, RidgeExpectation, cholesky_gram, kl_constrained
from r2pvi.duals import constrained as C


def ridge_operator(seed, n, d, signed, ties, zero_mass, scale):
    """Ridge weights with the hard cases: signed features, tied values (many at the minimum
    and the maximum), a factor with no mass at all (a feature that is always 0)."""
    rng = np.random.default_rng(seed)
    v = scale * rng.uniform(0.0, 1.0, size=n)
    if ties:
        v[rng.random(n) < 0.4] = 0.0
        v[rng.random(n) < 0.2] = scale
    phi = rng.dirichlet(np.full(d, 0.6), size=n)
    if signed:
        phi = phi - 0.1
    if zero_mass:
        phi[:, 0] = 0.0
    return RidgeExpectation(phi, cholesky_gram(phi, 1.0)), v


ridge_cases = st.tuples(
    st.integers(0, 2**31 - 1),  # seed
    st.integers(3, 150),  # n
    st.integers(1, 6),  # d
    st.booleans(),  # signed features
    st.booleans(),  # ties
    st.booleans(),  # a factor without mass
    st.sampled_from([1e-3, 1.0, 30.0, 1e6]),  # value scale
)


def problem(E, v, rho):
    d = E.n_dims
    plain = E(v)
    dims = np.arange(d)
    prob = C._KLProblem(E, v, np.full(d, rho), dims, 0.0, True)
    prob.set_cap(np.clip(plain, 0.0, v.max()))
    prob.on_grid(np.array([v.max() or 1.0]))  # E(1) arrives with the first grid
    return prob


@settings(max_examples=150, deadline=None)
@given(ridge_cases, st.floats(-6.0, 3.0), st.floats(-4.0, 0.5), st.integers(0, 2**31 - 1))
def test_series_evaluation_equals_the_exact_evaluation(case, log_rho, log_b, seed):
    """Per factor at its own b, anywhere: the series where a node is within the radius (added
    on demand), the exact form elsewhere; values and both derivatives as the exact form."""
    E, v = ridge_operator(*case)
    scale = case[-1]
    prob = problem(E, v, 10.0 ** log_rho)
    if not prob._series_possible():
        return
    rng = np.random.default_rng(seed)
    t0 = math.log(scale) + log_b
    prob._t_range = (t0 - 3.0, t0 + 16.0)
    d = E.n_dims
    prob._series_cover(np.array([t0]), None)
    idx = np.arange(d)
    # within the node's radius, on both sides, and far from it (new nodes or exact)
    # b >> max|V| (offset 14) takes the exact form, accurate for large b
    for offset in (0.0, C._SERIES_RADIUS, -C._SERIES_RADIUS, 0.5 * C._SERIES_RADIUS, 0.7, -1.3,
                   14.0):
        b = np.exp(t0 + offset + 1e-3 * rng.uniform(-1, 1, size=d) * (abs(offset) < 0.5))
        got = prob.per_factor(idx, b)
        want = prob._per_factor_exact(idx, b)
        g_tol = 1e-12 * scale
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=g_tol)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9, atol=1e-10 * scale)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-7, atol=1e-8 * scale)


@pytest.mark.parametrize("x_max", [0.0, 0.3, 3.3, 9.2, 40.0, 1e4])
def test_series_order_meets_its_truncation_bound(x_max):
    """The chosen order's series reproduces exp(-x (1 + beta)) on [0, x_max] to the bound
    (``_SERIES_TOL`` per unit weight) plus rounding, at the edge of the radius
    (beta = e^{+-R} - 1); half the order does not."""
    order = C._series_order(x_max)
    assert 0 <= order <= C._SERIES_ORDER
    x = np.linspace(0.0, x_max, 2001)
    k = np.arange(C._SERIES_ORDER + 1)
    terms = np.exp(k[None, :] * np.log(np.maximum(x, 1e-300))[:, None]
                   - np.array([math.lgamma(i + 1) for i in k])[None, :])
    terms[:, 0] = 1.0
    for beta in (math.expm1(C._SERIES_RADIUS), math.expm1(-C._SERIES_RADIUS)):
        powers = (-beta) ** k
        exact = np.exp(-x * (1.0 + beta))

        def series(n, powers=powers):
            return np.exp(-x) * (terms[:, :n + 1] * powers[:n + 1]).sum(axis=1)

        # the bound (1e-17 per unit weight) plus the rounding of the sum
        tol = C._SERIES_TOL + 2e-15 * np.exp(-x * (1.0 - abs(beta)))
        assert np.all(np.abs(series(order) - exact) <= tol)
        if x_max >= 1.0:  # the check can fail: half the order is far off
            assert np.any(np.abs(series(order // 2) - exact) > 100 * tol)


def reference(monkeypatch, *args, **kwargs):
    """``kl_constrained`` with the series switched off: a local grid of exact evaluations
    and exact per-factor Newton steps (the solver before the series)."""
    with monkeypatch.context() as m:
        m.setattr(C._KLProblem, "_series_possible", lambda self: False)
        return kl_constrained(*args, **kwargs)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(50, 400), st.integers(1, 8),
       st.floats(-3.0, 1.0), st.sampled_from([1e-3, 1.0, 1e6]))
def test_kl_ball_with_series_equals_the_exact_solver(seed, n, d, log_rho, scale):
    """Dirichlet features (as the benchmark's and the simulated MDPs'), b_min = "auto"'s
    value: the same maximum as the solver without the series, to rounding."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=n)
    v = scale * np.clip(phi @ rng.uniform(0.0, 1.0, d) + 0.1 * rng.normal(size=n), 0.0, None)
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    b_min = (v.max() - v.min()) / math.log(n) if v.max() > v.min() else None
    kw = {"v_range": (0.0, scale * 2.0), "centered": True, "b_min": b_min}
    rho = 10.0 ** log_rho * rng.uniform(0.5, 1.5, size=d)
    got = kl_constrained(E, v, rho, **kw)
    want = reference(pytest.MonkeyPatch(), E, v, rho, **kw)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * scale)


def test_kl_ball_series_on_exact_distributions(monkeypatch):
    """Exact distributions: a shared support minimum takes the series; different minima, or
    a lowest value no factor reaches (y < 0 there: exp(-y/b) overflows at small b), the exact
    path; all as the reference."""
    rng = np.random.default_rng(3)
    v = rng.uniform(0.0, 2.0, size=7)
    mu = rng.dirichlet(np.ones(7), size=3)
    shared = FactorExpectation(mu)
    mu_split = mu.copy()
    mu_split[1, np.argmin(v)] = 0.0  # factor 1 does not see the minimum
    split = FactorExpectation(mu_split / mu_split.sum(axis=1, keepdims=True))
    for E in (shared, split):
        for rho in (1e-4, 0.05, 0.5, 2.0):
            got = kl_constrained(E, v, rho)
            np.testing.assert_allclose(got, reference(monkeypatch, E, v, rho), rtol=1e-11,
                                       atol=1e-13)
    unreached = np.append(v, -5e3)  # the lowest value, on no factor's support
    E = FactorExpectation(np.hstack([mu, np.zeros((3, 1))]))
    for rho in (0.05, 0.5):
        got = kl_constrained(E, unreached, rho)
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, reference(monkeypatch, E, unreached, rho),
                                   rtol=1e-11, atol=1e-13)


def _shifted_reference(x0, x1, x2, m, b, c):
    """log u, t1, b3g2 of ``_KLProblem._shifted`` by the masked formulas (any signs)."""
    with np.errstate(all="ignore"):
        pos = x0 > 0
        q = np.where(x0 != 0, x1 / x0, 0.0)
        var = np.where(x0 != 0, x2 / x0, 0.0) - q * q
        p = x0 * np.exp(-m / b)
        u = p + c
        log_u = np.where(u > 0, np.log(np.where(u > 0, u, 1.0)), -np.inf)
        frac = np.where(u != 0, p / u, 0.0)
        mean = m + q
        return log_u, frac * mean / b, -frac * (var + (1.0 - frac) * mean * mean), pos


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_shifted_objective_without_masks_equals_the_masked_formulas(seed, negative_c):
    """The usual case (every X_0 > 0, every c > 0) skips the masks; rows with c <= 0
    (ridge rows summing to more than 1) must not."""
    rng = np.random.default_rng(seed)
    m = 12
    x0 = rng.uniform(0.01, 2.0, m)
    x1, x2 = x0 * rng.uniform(0.0, 1.0, m), x0 * rng.uniform(0.0, 1.0, m)
    shift, b = rng.uniform(0.0, 1.0, m), rng.uniform(0.05, 2.0, m)
    c = rng.uniform(-0.5, 0.9, m) if negative_c else rng.uniform(0.01, 0.9, m)
    prob = C._KLProblem.__new__(C._KLProblem)
    prob.centered = False

    def finish(log_u, t1, b3g2, b, rho, cap):
        return log_u, t1, b3g2

    prob._finish = finish
    got = prob._shifted(x0, x1, x2, shift, b, c, 0.0, 1.0)
    want = _shifted_reference(x0, x1, x2, shift, b, c)
    # Rounding bounds scaled by the conditioning of u = p + c (c < 0 cancels) and of the
    # variance term: 40,000 seeds of this generator stay below 7% of each bound; a wrong mask
    # is off by O(1) or non-finite.
    p = x0 * np.exp(-shift / b)
    u = p + c
    frac, q = p / u, x1 / x0
    mean = shift + q
    ku = (np.abs(p) + np.abs(c)) / np.abs(u)
    scales = (ku, ku * np.abs(want[1]),
              (ku + 1.0) * np.abs(frac) * (x2 / x0 + q * q + np.abs(1.0 - frac) * mean * mean))
    for g, w, scale in zip(got, want[:3], scales, strict=True):
        assert np.array_equal(np.isfinite(g), np.isfinite(w))
        ok = np.isfinite(w)
        assert np.all(np.abs(g[ok] - w[ok]) <= 1e-13 * scale[ok])


def _hermite_full(t0, t1, g0, d0, dd0, g1, d1, dd1, iters=12):
    """The quintic maximizer with every Newton iteration run (no early stop on cycles)."""
    h = t1 - t0
    with np.errstate(all="ignore"):
        c1, c2, c3, c4, c5 = C._quintic_coefficients(t0, t1, g0, d0, dd0, g1, d1, dd1)

        def quintic(x):
            return g0 + x * (c1 + x * (c2 + x * (c3 + x * (c4 + x * c5))))

        grid = [quintic(np.full_like(t0, x)) for x in C._HERMITE_GRID]
        j = np.argmax(np.stack(grid, axis=1), axis=1)  # start at the best grid point
        s = C._HERMITE_GRID[j]
        best = np.stack(grid, axis=1)[np.arange(j.size), j]
        for _ in range(iters):
            p1 = c1 + s * (2.0 * c2 + s * (3.0 * c3 + s * (4.0 * c4 + s * 5.0 * c5)))
            p2 = 2.0 * c2 + s * (6.0 * c3 + s * (12.0 * c4 + s * 20.0 * c5))
            s_new = np.clip(s - p1 / np.where(p2 < 0, p2, -np.inf), 0.0, 1.0)
            done = np.all(np.abs(s_new - s) <= 1e-13)
            s = s_new
            if done:
                break
        p1 = c1 + s * (2.0 * c2 + s * (3.0 * c3 + s * (4.0 * c4 + s * 5.0 * c5)))
        good = (h > 0) & (s > 0.0) & (s < 1.0) & np.isfinite(s) & np.isfinite(
            g0 + g1 + d0 + d1 + dd0 + dd1) & (np.abs(p1) <= 1e-6 * (np.abs(c1) + np.abs(h * d1)))
        size = sum(np.abs(c) for c in (g0, c1, c2, c3, c4, c5))
        good &= quintic(s) >= best - 1e-12 * size  # no lower than the best grid point
    return np.where(good, t0 + h * s, np.nan)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1e-3, 1.0, 1e3]))
def test_hermite_argmax_stops_on_cycles_where_the_full_iteration_ends(seed, scale):
    """Rows that bounce between the ends of [0, 1] no longer keep all rows iterating: the
    result (NaN pattern and maximizers) is the full iteration's."""
    rng = np.random.default_rng(seed)
    m = 30
    t0 = rng.normal(size=m)
    t1 = t0 + rng.uniform(0.0, 1.0, size=m)
    args = [scale * rng.normal(size=m) for _ in range(6)]
    got = C._hermite_argmax(t0, t1, *args)
    want = _hermite_full(t0, t1, *args)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    # the hoisted coefficients round differently: a starting point, ~1e-12 off
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
