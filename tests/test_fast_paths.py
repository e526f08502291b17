"""The fast paths of the duals (benchmarks/bench_fit.py) against their reference forms.

Each test targets one shortcut: it compares the shortcut with the computation it replaces
(or with brute force), on signed ridge weights where that matters.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.duals import RidgeExpectation, cholesky_gram, kl_constrained, kl_regularized
from r2pvi.duals._kl_series import _hermite_argmax
from r2pvi.duals._scratch import buffer, release
from r2pvi.duals.blockscan import BlockScan
from r2pvi.duals.sorting import BLOCK


def ridge(seed, n, d, signed=True):
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=(n, d)) if signed else rng.dirichlet(np.ones(d), size=n)
    return RidgeExpectation(phi, cholesky_gram(phi, 0.3)), rng


def test_buffer_reuses_its_memory_for_smaller_shapes_and_grows_for_larger():
    release()
    a = buffer("t.key", (4, 5))
    assert a.shape == (4, 5) and a.flags.c_contiguous
    b = buffer("t.key", (3, 2))
    assert b.shape == (3, 2) and b.flags.c_contiguous and np.shares_memory(a, b)
    c = buffer("t.key", (7, 7))
    assert c.shape == (7, 7) and not np.shares_memory(a, c)
    release()


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 40), st.sampled_from([1, 3, 8]),
       st.booleans())
def test_one_vector_regression_equals_the_factor_solve(seed, n, d, signed):
    E, rng = ridge(seed, n, d, signed)
    y = rng.uniform(-5, 5, size=n)
    ref = E.factor.regress(y)
    np.testing.assert_allclose(E(y), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([40, 200, 777]), st.sampled_from([2, 7]),
       st.booleans())
def test_block_slope_bounds_hold_on_every_segment(seed, n, d, ties):
    """``b_lo <= dE([V]_alpha)/dalpha <= b_hi`` on every segment of every block (the exact
    slopes from the dense cumulants), with signed ridge weights."""
    E, rng = ridge(seed, n, d)
    v = rng.integers(0, 5, size=n).astype(float) if ties else rng.exponential(size=n)
    scan = BlockScan(E, v, second_moment=False)
    cum = E.truncation_cumulants(v)  # cum.b[:, k]: the slope on segment k
    m = cum.b.shape[1]
    blk = np.arange(m) // BLOCK
    slack = 1e-9 * (1.0 + np.abs(cum.b).max())
    assert np.all(cum.b >= scan.b_lo[:, blk] - slack)
    assert np.all(cum.b <= scan.b_hi[:, blk] + slack)


def _hermite_of(p, t0, t1):
    """``_hermite_argmax`` on the Hermite data (values, two derivatives) of ``p`` at both ends."""
    dp, ddp = p.deriv(), p.deriv(2)
    a, b = np.array([t0]), np.array([t1])
    return _hermite_argmax(a, b, p(a), dp(a), ddp(a), p(b), dp(b), ddp(b))[0]


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.floats(-2, 2),
       st.floats(0.05, 1.5))
def test_hermite_argmax_starts_no_lower_than_its_grid(coef, t0, h):
    """Hermite data of a quintic determine it: the returned point (a starting point for the
    safeguarded Newton iteration, not the answer) is inside the interval and its value is at
    least the quintic's best on the 17-point start grid, so at most a maximum narrower than
    the grid's spacing is missed; or NaN when no interior maximum was certified."""
    p = np.polynomial.Polynomial(coef)
    t1 = t0 + h
    got = _hermite_of(p, t0, t1)
    if np.isnan(got):
        return  # allowed: the solver then bisects
    assert t0 < got < t1
    vals = p(np.linspace(t0, t1, 2001))
    assert p(got) >= p(t0 + h * np.linspace(0.0, 1.0, 17)).max() - 1e-9 * (
        1.0 + np.abs(vals).max())


def test_hermite_argmax_passes_a_stationary_inflection():
    """p(t) = t^3 - t^5 on [-0.25, 1.25]: p' = 0 at the inflection t = 0 (where Newton from
    the left end could stop, returning ~-5e-5) and at the maximum t = sqrt(3/5), which is
    found."""
    got = _hermite_of(np.polynomial.Polynomial([0, 0, 0, 1, 0, -1]), -0.25, 1.25)
    assert abs(got - np.sqrt(0.6)) < 1e-9


def test_hermite_argmax_refuses_non_finite_data():
    nan = np.array([np.nan])
    one = np.array([1.0])
    out = _hermite_argmax(np.array([0.0]), one, -np.inf * one, one, -one, one, -one, -one)
    assert np.isnan(out[0])
    out = _hermite_argmax(np.array([0.0]), one, one, nan, -one, one, -one, -one)
    assert np.isnan(out[0])


@pytest.mark.parametrize("lam", [0.05, 1.0, 30.0, 63.0])
def test_kl_without_expm1_matches_the_expm1_form(lam):
    """Below the expm1 threshold (lam <= 64 spreads) ``exp(z) - 1`` replaces ``expm1(z)``:
    the result matches the all-expm1 computation to 1e-13 of the values."""
    E, rng = ridge(3, 300, 6, signed=False)
    v = rng.uniform(0.0, 1.0, size=300)
    shift = v.min()
    z = -(v - shift) / lam
    u, um = E(np.exp(z)), E(np.expm1(z))
    s = u - um
    with np.errstate(divide="ignore", invalid="ignore"):
        log_norm = np.where(u > 0.5 * s, np.log1p(um / s), np.log(u / s))
    ref = s * (shift - lam * log_norm)
    got = kl_regularized(E, v, lam, v_max=10.0)
    ok = np.isfinite(ref)  # (a factor whose estimate u_i <= 0 is capped: other code path)
    assert ok.sum() >= 4
    np.testing.assert_allclose(got[ok], np.minimum(ref, 10.0)[ok], rtol=0, atol=1e-13)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([5, 1024, 2500]), st.sampled_from([1, 4]),
       st.booleans())
def test_apply_pair_equals_two_regressions(seed, n, d, weighted):
    """The chunked pair of regressions (one pass over the rows) equals two calls, for any n
    (a multiple of the chunk or not) and with variance weights (the fallback)."""
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=(n, d))
    w = rng.uniform(0.1, 2.0, size=n) if weighted else None
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.5, w), w)
    y1, y2 = rng.normal(size=n), rng.exponential(size=n)
    a, b = E.apply_pair(y1, y2)
    for got, y in ((a, y1), (b, y2)):
        ref = E.factor.regress(y)
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def _ma_objective(E, v, b, rho, v_max):
    """Ma et al.'s clipped ridge objective (as in test_constrained), at one b for all factors."""
    est = E(np.expm1(-v / b))
    with np.errstate(divide="ignore"):
        log_u = np.log(1.0 + np.clip(est, -1.0, 0.0))
    m = np.minimum(E(v), v_max)
    return -b * np.maximum(log_u, -m / b) - b * rho


@pytest.mark.parametrize("seed", [2, 3])
def test_kl_ball_local_grid_stays_above_b_min(seed):
    """``b_min`` between the two smallest maximizers (log b 0.06 apart on these seeds): the
    local grid around the other factors' estimates reaches below ``b_min``, where the first
    factor's objective is larger; it must not be evaluated there. The result is the maximum
    over ``b >= b_min``."""
    E, rng = ridge(seed, 400, 4, signed=False)
    v = rng.uniform(0.0, 3.0, size=400)
    rho = 0.2
    ts = np.linspace(np.log(1e-3), np.log(1e2), 3000)
    dense = np.array([_ma_objective(E, v, np.exp(t), rho, 3.0) for t in ts])
    t_star = np.sort(ts[dense.argmax(axis=0)])
    assert t_star[1] - t_star[0] < 0.1  # the setting this test needs
    b_min = float(np.exp(0.5 * (t_star[0] + t_star[1])))
    got = kl_constrained(E, v, rho, v_max=3.0, centered=True, b_min=b_min)
    allowed = np.linspace(np.log(b_min), np.log(1e2), 3000)
    grid = np.array([_ma_objective(E, v, np.exp(t), rho, 3.0) for t in allowed])
    best = grid.max(axis=0)
    for i, k in enumerate(grid.argmax(axis=0)):  # a finer local grid around each best cell
        local = np.linspace(allowed[max(k - 1, 0)], allowed[min(k + 1, allowed.size - 1)], 801)
        best[i] = max(best[i], max(_ma_objective(E, v, np.exp(t), rho, 3.0)[i] for t in local))
    assert np.all(got <= best + 1e-11)
    np.testing.assert_allclose(got, best, atol=1e-6)
