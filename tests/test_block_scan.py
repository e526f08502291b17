"""The branch and bound over blocks of sorted breakpoints (chi^2, TV ball) against brute force.

Each fast path of :mod:`r2pvi.duals.piecewise` and of ``RidgeExpectation.sorted_blocks`` is
checked against its reference form on ridge operators: signed weights, sample weights, ties,
zero-mass factors (an unused feature), extreme scales, negative values (blocks that straddle
0), padding and extra breakpoints.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi.duals import ExpectationOperator, RidgeExpectation, chi2_regularized, cholesky_gram
from r2pvi.duals.blockscan import BlockScan, _running_sums
from r2pvi.duals.piecewise import (
    _chi2_block_bounds,
    blockwise_max,
    chi2_objective,
    dense_max,
    segments_max,
    tv_ball_max,
)
from r2pvi.duals.ranges import value_extent
from r2pvi.duals.sorting import BLOCK, fine_blocks, sort_breakpoints, sort_order


def ridge_case(seed, n, d, *, signed, weighted, zero_mass, scale, negative, ties):
    """A ridge operator and values with the requested features."""
    rng = np.random.default_rng(seed)
    phi = rng.normal(size=(n, d)) if signed else rng.dirichlet(np.ones(d), size=n)
    if zero_mass and d > 1:
        phi[:, -1] = 0.0  # a factor no sample activates: a zero weight row
    w = rng.uniform(0.2, 2.0, n) if weighted else None
    E = RidgeExpectation(phi, cholesky_gram(phi, 0.3, w), w)
    v = rng.uniform(-1.0 if negative else 0.0, 1.0, n)
    if ties:
        v = np.round(v, 1)
    return E, v * scale


cases = st.fixed_dictionaries({
    "seed": st.integers(0, 2**31 - 1),
    "n": st.sampled_from([1, 15, 16, 37, 160, 333]),
    "d": st.sampled_from([1, 3, 6]),
    "signed": st.booleans(),
    "weighted": st.booleans(),
    "zero_mass": st.booleans(),
    "scale": st.sampled_from([1e-6, 1.0, 1e6]),
    "negative": st.booleans(),
    "ties": st.booleans(),
})


def _extra(v):
    """The breakpoint 0 the duals add when values straddle it."""
    return (0.0,) if v.min() < 0.0 < v.max() else ()


def _block_segments(E, v, extra):
    """Per block k of the sorted breakpoints, the exact segment coefficients of the dense
    cumulants covering it (its breakpoints and the next block's start)."""
    cum = E.truncation_cumulants(v, extra)
    a, b, c, al = (np.array(x) for x in (cum.a, cum.b, cum.c, cum.alphas))
    m = al.size
    for k in range(-(-m // BLOCK)):
        idx = np.arange(k * BLOCK, min((k + 1) * BLOCK + 1, m))
        yield k, a[:, idx], b[:, idx], c[:, idx], al[idx]


@settings(max_examples=60, deadline=None)
@given(cases, st.sampled_from([1e-3, 0.3, 10.0]),
       st.sampled_from(["none", "mean", "both", "negative_mean"]), st.sampled_from([1, 3, 4]))
def test_chi2_block_bound_is_at_least_the_exact_maximum_of_every_block(case, lam, clips, group):
    """``_chi2_block_bounds`` (its monotone shortcut, the convex case without a mean clip, the
    negative-alpha and straddle corrections) bounds the exact maximum of the objective over
    every block's segments, on both levels of the scan: blocks of ``16 group`` breakpoints and
    (:meth:`BlockScan.sub_blocks`) their blocks of 16, whose start values are exact."""
    E, v = ridge_case(**case)
    top = float(np.abs(v).max()) or 1.0
    mean_clip, second_clip = {
        "none": (None, None), "mean": ((0.0, top), None), "both": ((0.0, top), (0.0, top**2)),
        "negative_mean": ((-10.0 * lam - top, top), (0.0, top**2)),
    }[clips]
    extra = _extra(v)
    scan = BlockScan(E, v, extra, group=group)
    upper = _chi2_block_bounds(scan, lam, mean_clip, second_clip).copy()
    d, n_coarse = upper.shape
    rows = np.repeat(np.arange(d), n_coarse)
    sub = scan.sub_blocks(rows, np.tile(np.arange(n_coarse), d))
    sub_upper = _chi2_block_bounds(sub, lam, mean_clip, second_clip).copy()
    cum = E.truncation_cumulants(v, extra)
    first = np.arange(0, cum.alphas.size, BLOCK)
    e1 = cum.a[:, first] + cum.b[:, first] * cum.alphas[first]  # at every fine block start
    e2 = cum.c[:, first] + cum.b[:, first] * cum.alphas[first] ** 2
    valid = sub.valid
    scale = 1e-10 * (1.0 + top) ** 2 * (1.0 + np.abs(E.matrix).sum(axis=1).max())
    assert np.all(np.abs(sub.e1_start - e1[rows[:, None], sub.blocks])[valid] <= scale)
    assert np.all(np.abs(sub.e2_start - e2[rows[:, None], sub.blocks])[valid] <= scale)
    for k, a, b, c, al in _block_segments(E, v, extra):
        exact = segments_max(a, b, c, al, lam, mean_clip, second_clip)
        tol = 1e-9 * (1.0 + np.abs(exact)) + 1e-12 * (1.0 + top + 0.25 / lam * top**2)
        assert np.all(upper[:, k // group] >= exact - tol), (k, upper[:, k // group] - exact)
        fine = sub_upper.reshape(d, n_coarse * group)[:, k]
        assert np.all(fine >= exact - tol), (k, fine - exact)


@settings(max_examples=60, deadline=None)
@given(cases, st.floats(0.0, 2.0), st.sampled_from([None, 1, 2, 3, 8]))
def test_tv_ball_blockwise_equals_every_breakpoint(case, rho, group):
    """``tv_ball_max`` (the same two-level scan, its TV bound) equals the maximum over every
    breakpoint of the dense cumulants."""
    E, v = ridge_case(**case)
    y = v - v.min()
    rho_d = np.full(E.n_dims, rho)
    got = tv_ball_max(E, y, rho_d, group=group)
    cum = E.truncation_cumulants(y)
    ref = (cum.a + (cum.b - rho_d[:, None]) * cum.alphas).max(axis=1)
    scale = 1.0 + np.abs(ref).max()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * scale)


@settings(max_examples=60, deadline=None)
@given(cases, st.sampled_from([1e-3, 0.3, 10.0]), st.booleans(),
       st.sampled_from([None, 1, 2, 3, 8]))
def test_chi2_blockwise_equals_dense_without_centering(case, lam, clipped, group):
    """The two-level branch and bound on uncentered values (negative alphas, a block
    straddling 0; any number of fine blocks per block, the last one short) equals the dense
    reference."""
    E, v = ridge_case(**case)
    top = float(np.abs(v).max()) or 1.0
    clips = ((0.0, top), (0.0, top**2)) if clipped else (None, None)
    extra = _extra(v)
    with np.errstate(over="ignore", invalid="ignore"):
        dense = dense_max(E, v, lam, *clips, extra).copy()
        block = blockwise_max(E, v, lam, *clips, extra, group=group)
    tol = 1e-9 * (1.0 + np.abs(dense).max()) + 1e-12 * 0.25 / lam * top**2
    np.testing.assert_allclose(block, dense, rtol=0, atol=tol)


@settings(max_examples=60, deadline=None)
@given(cases, st.booleans())
def test_ridge_sorted_blocks_equal_the_explicit_weights(case, with_extra):
    """The feature-space block sums of the ridge operator (Lambda^-1 applied to the transposed
    sums, no padding checks when there is no padding) equal the block sums of the explicit
    weight columns; its bound on the sums of |M| holds; the pairs' weights are exact."""
    E, v = ridge_case(**case)
    extra = (0.5 * (v.min() + v.max()),) if with_extra else ()
    fast = E.sorted_blocks(v, extra)
    s = [np.array(x) for x in (fast.s0, fast.s1, fast.s2, fast.sabs)]
    ref = ExpectationOperator.sorted_blocks(E, v, extra)
    scale = 1.0 + np.abs(E.matrix).sum(axis=1, keepdims=True) * (1.0 + np.abs(v).max()) ** 2
    for got, want in zip(s[:3], (ref.s0, ref.s1, ref.s2), strict=True):
        assert np.all(np.abs(got - want) <= 1e-10 * scale), np.abs(got - want).max()
    assert np.all(s[3] >= ref.sabs - 1e-10 * scale)
    np.testing.assert_array_equal(fast.alphas, ref.alphas)
    rows = np.repeat(np.arange(E.n_dims), s[0].shape[1])
    blocks = np.tile(np.arange(s[0].shape[1]), E.n_dims)
    np.testing.assert_allclose(fast.pairs(rows, blocks), ref.pairs(rows, blocks), rtol=0,
                               atol=1e-10 * np.abs(E.matrix).max() + 1e-300)


@given(st.integers(1, 100), st.integers(0, 2), st.integers(0, 2**31 - 1))
def test_sort_breakpoints_pads_and_marks_extra_points(n, n_extra, seed):
    """``src`` holds every point of v once and -1 for extras and padding; without either it is
    the sort order itself."""
    rng = np.random.default_rng(seed)
    v = rng.integers(0, 5, n).astype(float)  # ties
    extra = tuple(rng.uniform(0, 5, n_extra))
    alphas, src, m = sort_breakpoints(v, extra)
    assert alphas.size % BLOCK == 0 and m == n + n_extra
    assert np.all(np.diff(alphas) >= 0)
    np.testing.assert_array_equal(np.sort(src[src >= 0]), np.arange(n))
    mask = src[:m] >= 0
    np.testing.assert_array_equal(alphas[:m][mask], v[src[:m][mask]])
    assert (src < 0).sum() == alphas.size - n
    np.testing.assert_array_equal(np.sort(alphas[:m][~mask]), np.sort(extra))


def test_scan_start_values_are_the_exact_objective_at_block_starts():
    """``e1_start`` / ``e2_start`` equal the dense cumulants at every block's first breakpoint
    (the values the bounds start from)."""
    E, v = ridge_case(3, 333, 5, signed=True, weighted=True, zero_mass=True, scale=1.0,
                      negative=True, ties=False)
    extra = _extra(v)
    scan = BlockScan(E, v, extra)
    cum = E.truncation_cumulants(v, extra)
    first = np.arange(0, cum.alphas.size, BLOCK)
    e1 = cum.a[:, first] + cum.b[:, first] * cum.alphas[first]
    e2 = cum.c[:, first] + cum.b[:, first] * cum.alphas[first] ** 2
    np.testing.assert_allclose(scan.e1_start, e1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(scan.e2_start, e2, rtol=0, atol=1e-12)
    g = chi2_objective(scan.e1_start, scan.e2_start, 0.3)
    np.testing.assert_allclose(g, chi2_objective(e1, e2, 0.3), rtol=0, atol=1e-11)


@settings(max_examples=40, deadline=None)
@given(cases, st.sampled_from([2, 3, 4]), st.booleans())
def test_ridge_coarse_and_fine_block_sums_equal_the_explicit_weights(case, group, moments3):
    """With ``group > 1`` the ridge operator maps only the sums over blocks of ``16 group`` by
    Lambda^-1 and the sums of the blocks of 16 inside chosen blocks on demand (``fine``); both
    equal the sums of the explicit weight columns (``sabs``: at least), past-the-end blocks of
    16 repeat the last one, and the generic operator gives the same."""
    E, v = ridge_case(**case)
    moments = 3 if moments3 else 2
    fast = E.sorted_blocks(v, (), moments=moments, group=group)
    ref = ExpectationOperator.sorted_blocks(E, v, (), moments=moments)  # blocks of 16
    generic = ExpectationOperator.sorted_blocks(E, v, (), moments=moments, group=group)
    names = ("s0", "s1", "s2", "sabs")
    scale = 1.0 + np.abs(E.matrix).sum(axis=1, keepdims=True) * (1.0 + np.abs(v).max()) ** 2
    d, nb = ref.s0.shape
    nc = -(-nb // group)
    starts = np.arange(0, nb, group)
    for name in names[:3] if moments3 else names[:2]:
        want = np.add.reduceat(getattr(ref, name), starts, axis=1)
        for got in (getattr(fast, name), getattr(generic, name)):
            assert got.shape == (d, nc)
            assert np.all(np.abs(got - want) <= 1e-10 * scale)
    want_abs = np.add.reduceat(ref.sabs, starts, axis=1)
    assert np.all(fast.sabs >= want_abs - 1e-10 * scale)
    assert fast.s2 is None if not moments3 else fast.s2 is not None
    rng = np.random.default_rng(case["seed"])
    rows = rng.integers(0, d, 7)
    blocks = rng.integers(0, nc, 7)  # repeated and distinct blocks, any order
    idx = fine_blocks(blocks, group, nb)
    assert np.all(idx == np.minimum(blocks[:, None] * group + np.arange(group), nb - 1))
    for sums, sabs in (fast.fine(rows, blocks), generic.fine(rows, blocks)):
        assert sums.shape == (moments, rows.size, group) and sabs.shape == (rows.size, group)
        for name, x in zip(names[:moments] + ("sabs",), (*sums, sabs), strict=True):
            want = getattr(ref, name)[rows[:, None], idx]
            tol = 1e-10 * scale[rows][:, :1]
            if name == "sabs":
                assert np.all(x >= want - tol)
            else:
                assert np.all(np.abs(x - want) <= tol), np.abs(x - want).max()


def _near_ties(rng, n):
    """Values that differ only in their last bits (and exact ties, both zeros, infinities)."""
    base = rng.choice([0.0, -0.0, 1.0, -3.5, 1e300, -1e-300, np.inf, -np.inf], n)
    ulps = rng.integers(-40, 40, n).astype(float)
    return np.where(np.isfinite(base), base + ulps * np.spacing(base), base)


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1, 2, 17, 300, 4099]),
       st.sampled_from(["uniform", "normal", "near_ties", "ties", "wide", "nan"]))
def test_sort_order_is_a_sorting_permutation(seed, n, kind):
    """``sort_order`` (integer keys with the index in their last bits, then the runs of values
    equal but for those bits sorted by value) sorts like ``np.argsort``: a permutation with
    the values non-decreasing, the sorted values written into ``out``; with NaN, exactly
    ``np.argsort``."""
    rng = np.random.default_rng(seed)
    v = {
        "uniform": lambda: rng.uniform(0.0, 1.0, n),
        "normal": lambda: rng.normal(size=n),
        "near_ties": lambda: _near_ties(rng, n),
        "ties": lambda: rng.integers(-3, 3, n) * 0.5,
        "wide": lambda: rng.normal(size=n) * 10.0 ** rng.integers(-300, 300, n),
        "nan": lambda: np.where(rng.random(n) < 0.2, np.nan, rng.normal(size=n)),
    }[kind]()
    if kind == "nan":
        v[rng.integers(0, n)] = -np.nan  # sign bit set: its key sorts first
    before = v.copy()
    out = np.empty(n)
    order = sort_order(v, out=out)
    np.testing.assert_array_equal(v, before)  # input unchanged
    np.testing.assert_array_equal(np.sort(order), np.arange(n))
    np.testing.assert_array_equal(out, v[order])
    np.testing.assert_array_equal(out, np.sort(v))  # NaN last, as np.sort
    if kind == "nan":
        np.testing.assert_array_equal(order, np.argsort(v))
    np.testing.assert_array_equal(sort_order(v), order)


@pytest.mark.parametrize("sign", [1, -1])
@pytest.mark.parametrize("n", [5, 40, 3000])
def test_sort_order_sees_a_nan_whose_payload_lies_in_the_index_bits(sign, n):
    """A NaN whose mantissa bits all lie in the last bits replaced by the index has the key
    of an infinity of its sign: it shares that infinity's run and could hide in the middle of
    the sort (as in ``[0.5, 1, 2, nan, inf]``). The order is still exactly ``np.argsort``'s."""
    rng = np.random.default_rng(n)
    v = rng.normal(size=n)
    payload = np.array([(0x7FF0000000000001 if sign > 0 else -0x000FFFFFFFFFFFFF)],
                       dtype=np.int64).view(np.float64)[0]  # +-NaN, payload in bit 0
    v[n // 3] = payload
    v[n // 2] = sign * np.inf
    assert np.isnan(payload)
    order = sort_order(v)
    np.testing.assert_array_equal(order, np.argsort(v))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 20), st.booleans(),
       st.sampled_from(["finite", "inf", "nan", "huge"]))
def test_running_sums_equal_cumsum(seed, n, exclusive, kind):
    """``_running_sums`` (a product with a triangle of ones up to 16 entries) equals
    ``np.cumsum`` (shifted by one if ``exclusive``), also where an entry is infinite or NaN
    (there the product would give NaN for the earlier sums: it falls back)."""
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(3, 5, n)) * 10.0 ** rng.integers(-5, 5, (3, 5, n))
    if kind != "finite":
        s[rng.integers(0, 3), rng.integers(0, 5), rng.integers(0, n)] = {
            "inf": np.inf, "nan": np.nan, "huge": 1.7e308}[kind]
    with np.errstate(over="ignore", invalid="ignore"):
        if kind == "huge":
            s[..., 0] = 1.7e308  # the sums overflow
        got = _running_sums(s, np.empty_like(s), exclusive)
        want = np.cumsum(s, axis=-1)
        scale = np.abs(s).cumsum(axis=-1)
        if exclusive:
            want = np.concatenate([np.zeros((3, 5, 1)), want[..., :-1]], axis=-1)
            scale = np.concatenate([np.zeros((3, 5, 1)), scale[..., :-1]], axis=-1)
        finite = np.isfinite(want)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_array_equal(got[~finite], want[~finite])
        assert np.all(np.abs(got - want)[finite] <= 1e-14 * scale[finite])


@settings(max_examples=40, deadline=None)
@given(cases, st.booleans(), st.booleans())
def test_chi2_with_the_extent_given_is_bitwise_the_same(case, clipped, center):
    """``chi2_regularized(..., extent=value_extent(v))`` (the rule's min/max handed over, the
    centered values' extent derived from it; uncentered, it decides the extra breakpoint 0)
    returns exactly what it computes by itself."""
    E, v = ridge_case(**case)
    top = float(np.abs(v).max()) or 1.0
    clips = ((0.0, top), (0.0, top**2)) if clipped else (None, None)
    with np.errstate(over="ignore", invalid="ignore"):
        alone = chi2_regularized(E, v, 0.3, *clips, center=center).copy()
        given_ = chi2_regularized(E, v, 0.3, *clips, center=center, extent=value_extent(v))
    np.testing.assert_array_equal(given_, alone)
