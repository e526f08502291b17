"""DRVI-L's fast paths (``kl_constrained``, benchmarks/bench_fit.py) against their reference forms.

The grid and the Newton steps of the KL-ball dual evaluate each factor at its own ``b`` from
Chebyshev moments (``_cheb_*``: ``b`` from ``max y / _CHEB_X`` up to the values' scale) or
from Taylor moments kept at a few shared nodes (``_series_*``: smaller ``b``) instead of ``n``
exponentials per factor; the reference is the exact per-factor evaluation
(``_per_factor_exact``) and, end to end, the solver with both switched off (a local grid of
exact evaluations).
"""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from r2pvi.duals import FactorExpectation, RidgeExpectation, cholesky_gram, kl_constrained
from r2pvi.duals import _kl_ball as C
from r2pvi.duals import _kl_series as S


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
    for offset in (0.0, S._SERIES_RADIUS, -S._SERIES_RADIUS, 0.5 * S._SERIES_RADIUS, 0.7, -1.3,
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
    order = S._series_order(x_max)
    assert 0 <= order <= S._SERIES_ORDER
    x = np.linspace(0.0, x_max, 2001)
    k = np.arange(S._SERIES_ORDER + 1)
    terms = np.exp(k[None, :] * np.log(np.maximum(x, 1e-300))[:, None]
                   - np.array([math.lgamma(i + 1) for i in k])[None, :])
    terms[:, 0] = 1.0
    for beta in (math.expm1(S._SERIES_RADIUS), math.expm1(-S._SERIES_RADIUS)):
        powers = (-beta) ** k
        exact = np.exp(-x * (1.0 + beta))

        def series(n, powers=powers):
            return np.exp(-x) * (terms[:, :n + 1] * powers[:n + 1]).sum(axis=1)

        # the bound (1e-17 per unit weight) plus the rounding of the sum
        tol = S._SERIES_TOL + 2e-15 * np.exp(-x * (1.0 - abs(beta)))
        assert np.all(np.abs(series(order) - exact) <= tol)
        if x_max >= 1.0:  # the check can fail: half the order is far off
            assert np.any(np.abs(series(order // 2) - exact) > 100 * tol)


def reference(monkeypatch, *args, **kwargs):
    """``kl_constrained`` with the Chebyshev and Taylor moments switched off: a local grid of
    exact evaluations and exact per-factor Newton steps (the reference solver)."""
    with monkeypatch.context() as m:
        m.setattr(C._KLProblem, "_series_possible", lambda self: False)
        return kl_constrained(*args, **kwargs)


def _dense_normalized(E, v, rho, b_min, cap_hi):
    """DRVI-L's normalized objective maximized by a dense search over ``b`` (independent of
    the solver): ``s_i max_b (-b log E_w[e^{-v/b}] - b rho_i)`` with the row-normalized ridge
    weights ``w`` and the plain estimate as the cap, as in the interior-maximum test."""
    rows = E.rows()
    out = np.empty(rows.shape[0])
    for i, row in enumerate(rows):
        s = row.sum()
        cap = np.clip(row @ v, 0.0, cap_hi) / s
        bs = np.geomspace(b_min, 2 * v.max() / rho[i], 200_001)
        u = np.maximum(np.exp(-v[None] / bs[:, None]) @ (row / s), np.exp(-cap / bs))
        out[i] = s * np.max(-bs * np.log(u) - bs * rho[i])
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(50, 400), st.integers(1, 8),
       st.floats(-3.0, 1.0), st.sampled_from([1e-3, 1.0, 1e6]), st.booleans())
@example(229, 229, 5, -1.677734375, 1e-3, True)  # an interior maximum the reference misses
def test_kl_ball_with_series_equals_the_exact_solver(seed, n, d, log_rho, scale, normalized):
    """Dirichlet features (as the benchmark's and the simulated MDPs'), b_min = "auto"'s
    value, Ma et al.'s centered form and DRVI-L's normalized one: the same maximum as the
    solver without the Chebyshev and Taylor moments, to rounding -- or a higher one that a
    dense search confirms (the reference's coarse grid can miss an interior maximum of a
    non-concave ridge objective that the Chebyshev range's fine grid finds)."""
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=n)
    v = scale * np.clip(phi @ rng.uniform(0.0, 1.0, d) + 0.1 * rng.normal(size=n), 0.0, None)
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    b_min = (v.max() - v.min()) / math.log(n) if v.max() > v.min() else None
    kw = {"v_range": (0.0, scale * 2.0), "b_min": b_min,
          "normalized" if normalized else "centered": True}
    rho = 10.0 ** log_rho * rng.uniform(0.5, 1.5, size=d)
    got = kl_constrained(E, v, rho, **kw)
    want = reference(pytest.MonkeyPatch(), E, v, rho, **kw)
    close = np.isclose(got, want, rtol=1e-10, atol=1e-12 * scale)
    if not close.all():
        assert normalized, (got, want)  # the centered form: no difference expected
        assert np.all(got[~close] > want[~close]), (got, want)
        dense = _dense_normalized(E, v, rho, b_min, scale * 2.0)
        np.testing.assert_allclose(got[~close], dense[~close], rtol=1e-9)


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
        c1, c2, c3, c4, c5 = S._quintic_coefficients(t0, t1, g0, d0, dd0, g1, d1, dd1)

        def quintic(x):
            return g0 + x * (c1 + x * (c2 + x * (c3 + x * (c4 + x * c5))))

        grid = [quintic(np.full_like(t0, x)) for x in S._HERMITE_GRID]
        j = np.argmax(np.stack(grid, axis=1), axis=1)  # start at the best grid point
        s = S._HERMITE_GRID[j]
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
    """Rows that bounce between the ends of [0, 1] stop (they do not keep all rows
    iterating), and the result (NaN pattern and maximizers) is the full iteration's."""
    rng = np.random.default_rng(seed)
    m = 30
    t0 = rng.normal(size=m)
    t1 = t0 + rng.uniform(0.0, 1.0, size=m)
    args = [scale * rng.normal(size=m) for _ in range(6)]
    got = S._hermite_argmax(t0, t1, *args)
    want = _hermite_full(t0, t1, *args)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    # the hoisted coefficients round differently: a starting point, ~1e-12 off
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


def test_cheb_matrix_gives_numpys_chebyshev_interpolant():
    """``_CHEB_MATRIX @ f(_CHEB_S)`` are the coefficients of the interpolant at the Chebyshev
    points of the first kind, as ``numpy.polynomial.chebyshev.chebinterpolate`` computes them."""
    for x in (0.5, 4.0, S._CHEB_X):
        def f(s, x=x):
            return np.exp(-0.5 * x * (s + 1.0))
        want = np.polynomial.chebyshev.chebinterpolate(f, S._CHEB_TERMS - 1)
        np.testing.assert_allclose(S._CHEB_MATRIX @ f(S._CHEB_S), want, rtol=0, atol=1e-14)


@pytest.mark.parametrize("x_cap", [0.3, 2.0, 9.0, S._CHEB_X, 40.0])
def test_cheb_terms_meet_their_interpolation_bound(x_cap):
    """The interpolant at ``_cheb_terms(x_cap)`` Chebyshev points reproduces ``y^j exp(-y/b)``
    (j = 0, 1, 2) on [0, 1] within ``tol b^j max(1, x)^j`` at the range's edge ``b = 1/x_cap``
    and above; computed in extended precision (the bound is below double rounding). Half as
    many points do not."""
    if np.finfo(np.longdouble).eps > 1e-18:
        pytest.skip("needs an extended-precision long double (x86)")
    tol = 1e-17
    m = S._cheb_terms(x_cap, tol)
    pi = np.longdouble("3.14159265358979323846264338327950288")
    y_dense = np.linspace(np.longdouble(0), np.longdouble(1), 4001)

    def interpolant(points, b, j):
        r = np.arange(points, dtype=np.longdouble)
        s = np.cos(pi * (r + np.longdouble(0.5)) / points)
        y = (s + 1) / 2
        vals = y ** j * np.exp(-y / b)
        k = np.arange(points, dtype=np.longdouble)
        coef = (2 / np.longdouble(points)) * (np.cos(pi * np.outer(k, r + np.longdouble(0.5))
                                                     / points) @ vals)
        coef[0] /= 2
        return np.polynomial.chebyshev.chebval(2 * y_dense - 1, coef)

    for b in (1 / np.longdouble(x_cap), 2 / np.longdouble(x_cap)):
        x = float(1 / b)
        for j in (0, 1, 2):
            exact = y_dense ** j * np.exp(-y_dense / b)
            bound = tol * float(b) ** j * max(1.0, x) ** j
            err = float(np.max(np.abs(interpolant(m, b, j) - exact)))
            assert err <= bound + 1e-18, (b, j, err, bound)
            if x_cap >= 2.0 and b < 1.5 / x_cap:  # the check can fail
                err_half = float(np.max(np.abs(interpolant(m // 2, b, j) - exact)))
                assert err_half > 100 * bound


@settings(max_examples=150, deadline=None)
@given(ridge_cases, st.floats(-6.0, 3.0), st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_cheb_evaluation_equals_the_exact_evaluation(case, log_rho, where, seed):
    """Per factor at its own b in the Chebyshev range ``[max y / _CHEB_X, scale)`` (ridge
    weights with signs, ties, a factor without mass, scales 1e-3 to 1e6), and below and above
    it once the Chebyshev moments are known (the routing): values and both derivatives as
    the exact form."""
    E, v = ridge_operator(*case)
    scale = case[-1]
    prob = problem(E, v, 10.0 ** log_rho)
    if not prob._series_possible() or not np.isfinite(prob._b_cheb):
        return
    lo, hi = math.log(prob._b_cheb), math.log(prob.scale)
    prob.on_grid(np.array([math.exp(lo + 0.5 * (hi - lo))]))  # brings the Chebyshev moments
    assert prob._cheb is not None
    d = E.n_dims
    rng = np.random.default_rng(seed)
    t = lo + (hi - lo) * np.clip(where + 0.05 * rng.uniform(-1, 1, size=d), 0.0, 0.999999)
    idx = np.arange(d)
    # in the range, and below and above it (Taylor nodes or the exact form, not the
    # Chebyshev moments, which would be 2e-10 off 1.5 below the range)
    for tt in (t, np.full(d, lo - 1.5), np.full(d, lo - 0.4), np.full(d, hi + 1.0)):
        b = np.exp(tt)
        got = prob.per_factor(idx, b)
        want = prob._per_factor_exact(idx, b)
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-12 * scale)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9, atol=1e-10 * scale)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-7, atol=1e-8 * scale)


def test_newton_steps_of_a_benchmark_step_make_no_pass(monkeypatch):
    """The benchmark's kind of step (Dirichlet features, DRVI-L's normalized form and b_min;
    radii whose maximizers lie in the Chebyshev range): the grid and every Newton step are
    served by the Chebyshev moments: no per-factor exact evaluation (n exponentials each) and
    one operator call on the step's points besides E(v), the grid's. The values equal the
    exact solver's."""
    rng = np.random.default_rng(0)
    n, d = 3000, 12
    phi = rng.dirichlet(np.ones(d), size=n)
    v = rng.dirichlet(np.ones(d), size=n) @ rng.uniform(0.0, 5.0, d)  # next states' values
    E = RidgeExpectation(phi, cholesky_gram(phi, 1.0))
    kw = {"v_range": (0.0, 6.0), "normalized": True, "b_min": (v.max() - v.min()) / math.log(n)}
    exact, cheb, call = (C._KLProblem._per_factor_exact, C._KLProblem._cheb_at,
                         RidgeExpectation.__call__)

    def count(key, fn):
        def wrapped(*a, **k):
            calls[key] += 1
            return fn(*a, **k)
        return wrapped

    for rho in (0.01, 0.03, 0.1):
        calls = {"exact": 0, "cheb": 0, "operator": 0}
        with monkeypatch.context() as m:
            m.setattr(C._KLProblem, "_per_factor_exact", count("exact", exact))
            m.setattr(C._KLProblem, "_cheb_at", count("cheb", cheb))
            m.setattr(RidgeExpectation, "__call__", count("operator", call))
            got = kl_constrained(E, v, rho, **kw)
        assert calls["exact"] == 0 and calls["cheb"] > 0, calls
        assert calls["operator"] == 2, calls  # E(v) and the grid with the Chebyshev basis
        np.testing.assert_allclose(got, reference(pytest.MonkeyPatch(), E, v, rho, **kw),
                                   rtol=1e-10, atol=1e-12)


@settings(max_examples=150, deadline=None)
@given(ridge_cases, st.floats(0.0, 1.0))
def test_cheb_moments_equal_the_direct_moments(case, where):
    """The Chebyshev moments' ``E_i[y^j exp(-y/b)]`` against the explicit weight rows, per
    unit of ``|weight|`` (and of ``b^j max(1, max y / b)^j``), across the range: the rounding
    of the two forms (~3e-15 measured), not the truncation (~4e-10 with 10 points fewer)."""
    E, v = ridge_operator(*case)
    prob = problem(E, v, 0.1)
    if not prob._series_possible() or not np.isfinite(prob._b_cheb):
        return
    lo, hi = math.log(prob._b_cheb), math.log(prob.scale)
    prob.on_grid(np.array([math.exp(0.5 * (lo + hi))]))
    rows = prob._weight_rows() / prob.norm[:, None]
    y = prob._y_shared
    b = math.exp(lo + where * (hi - lo) * 0.999999)
    coef = prob._cheb_coefficients(np.array([b]))
    for j in range(3):
        got = prob._cheb @ coef[j, 0]
        want = rows @ (y ** j * np.exp(-y / b))
        unit = np.abs(rows).sum(axis=1) * b ** j * max(1.0, prob._y_max / b) ** j
        assert np.all(np.abs(got - want) <= 2e-14 * unit + 1e-300), (j, got - want, unit)


def test_cheb_objective_is_relatively_accurate_for_mass_at_the_top():
    """A ridge factor whose mass sits at the largest values (``E_i[e^{-y/b}]`` as small as
    ``e^{-6}`` at the range's lower end): the Chebyshev route's objective within 2e-13
    (relative) of the exact evaluation across the range (the bound of ``_CHEB_X``'s comment;
    a range down to ``max y / 16`` would be 5e-10 off)."""
    for seed in range(10):
        rng = np.random.default_rng(seed)
        n, d = 400, 5
        v = rng.uniform(0.0, 1.0, n)
        v[0] = 0.0
        top = (v > 0.97).astype(float)
        phi = np.hstack([top[:, None],
                         0.5 * rng.dirichlet(np.ones(d - 1), size=n) * (1.0 - top[:, None])])
        E = RidgeExpectation(phi, cholesky_gram(phi, 1e-3))
        prob = C._KLProblem(E, v, np.full(d, 0.1), np.arange(d), 0.0, False, normalized=True)
        prob.set_cap(np.clip(E(v), 0.0, 1.0))
        prob.on_grid(np.array([1.0]))
        lo, hi = math.log(prob._b_cheb), math.log(prob.scale)
        prob.on_grid(np.array([math.exp(0.5 * (lo + hi))]))
        assert prob._cheb is not None
        idx = np.arange(d)
        for t in (lo + 1e-12, lo + 0.3, 0.5 * (lo + hi)):
            b = np.full(d, math.exp(t))
            got, want = prob.per_factor(idx, b)[0], prob._per_factor_exact(idx, b)[0]
            np.testing.assert_allclose(got, want, rtol=2e-13, atol=0)


def test_interior_maximum_between_coarse_grid_points_is_found():
    """Seed 395 with DRVI-L's defaults (normalized form, b_min = spread / log n): factor 0's
    objective is not concave and peaks between b_min and the next coarse grid point; the
    result is the dense search's maximum (a search of the coarse grid alone returns 3.7e-5
    less)."""
    rng = np.random.default_rng(395)
    n = int(rng.choice([20, 60, 200]))
    d = int(rng.choice([4, 8, 16]))
    phi = rng.dirichlet(np.full(d, 0.5), size=n)
    nphi = rng.dirichlet(np.full(d, 0.5), size=(n, 3))
    v = np.clip((nphi @ rng.uniform(0, 1, d)).max(axis=1), 0, None)
    rho = float(10 ** rng.uniform(-3, 0.5))
    b_min = (v.max() - v.min()) / np.log(n)
    got = kl_constrained(RidgeExpectation(phi, cholesky_gram(phi, 1.0)), v, rho,
                         v_range=(0.0, 2.0), normalized=True, b_min=b_min)
    rows = np.linalg.solve(phi.T @ phi + np.eye(d), phi.T)  # the ridge weights, explicitly
    for i in range(d):
        s = rows[i].sum()
        w = rows[i] / s
        cap = np.clip(rows[i] @ v, 0.0, 2.0) / s
        bs = np.geomspace(b_min, 2 * v.max() / rho, 100_001)
        u = np.maximum(np.exp(-v[None] / bs[:, None]) @ w, np.exp(-cap / bs))
        dense = s * np.max(-bs * np.log(u) - bs * rho)
        assert got[i] >= dense - 1e-12 * np.abs(v).max(), (i, got[i], dense)
        assert got[i] <= min(s * cap, dense + 1e-6), (i, got[i], dense)


@pytest.mark.parametrize("p, rho", [(1.32e-9, 0.163), (1.2e-10, 0.0124), (0.3, 0.05),
                                    (1e-4, 0.1508)])
def test_exact_two_point_distribution_is_exact(p, rho):
    """Exact distributions keep the relatively accurate Taylor path: mass p at V = 0, 1 - p at
    V = 1 (cases where the Chebyshev route would be 5e-10 off; the last has its maximizer
    b = 0.17 inside what would be the Chebyshev range): the result
    equals the maximum of ``-b log(p + (1 - p) e^{-1/b}) - b rho`` found by a bounded scalar
    search, to 1e-14."""
    from scipy.optimize import minimize_scalar

    def g(t):
        b = math.exp(t)
        return -b * (np.logaddexp(math.log(p), math.log1p(-p) - 1.0 / b) + rho)

    best = minimize_scalar(lambda t: -g(t), bounds=(math.log(1e-4), math.log(1e3)),
                           method="bounded", options={"xatol": 1e-12})
    want = g(best.x)
    got = kl_constrained(FactorExpectation(np.array([[p, 1.0 - p]])), np.array([0.0, 1.0]), rho)
    np.testing.assert_allclose(got[0], want, rtol=1e-14, atol=1e-15)
