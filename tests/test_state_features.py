"""State features stored once per observation (data.storage.crossed) stand for the dense
rows exactly, and pooled fits on them (one operator, the penalty formed once, a stop at a
fixed point) give the numbers of the dense rows and of the full loop."""

from unittest.mock import patch

import numpy as np
import pytest
from helpers import pooled_or_per_step_estimators
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import R2PVI, OfflineDataset
from r2pvi.data.storage.crossed import CrossedRows, cross_rows
from r2pvi.duals import crossed_blocks
from r2pvi.engine import backward_induction
from r2pvi.engine.pooled import CrossedRidgeExpectation, PooledNextValues
from r2pvi.engine.q import _NextValue
from r2pvi.features import NormalizedRBF, cross_actions

FAST = settings(max_examples=25, deadline=None)


def _episodes(rng, K, obs_dim=2, max_len=7, H=None):
    """Episodes of random lengths, some terminated, some truncated or longer than H."""
    eps = []
    for _ in range(K):
        T = int(rng.integers(1, max_len + 1))
        term = np.zeros(T, dtype=bool)
        trunc = np.zeros(T, dtype=bool)
        if rng.random() < 0.5:
            term[-1] = True
        else:
            trunc[-1] = True
        eps.append({"observations": rng.random((T + 1, obs_dim)),
                    "actions": rng.integers(0, 2, T), "rewards": rng.random(T),
                    "terminations": term, "truncations": trunc})
    return eps


def _both(eps, H, bins=3, **kw):
    """The same episodes in the state-feature layout and as dense rows (a plain callable
    map is not recognised as crossed)."""
    fmap = cross_actions(NormalizedRBF(n_centers=bins).fit(np.array([[0.0, 0.0], [1.0, 1.0]])),
                         2)
    crossed = OfflineDataset.from_episodes(eps, fmap, 2, horizon=H, **kw)
    dense = OfflineDataset.from_episodes(eps, lambda o, a: fmap(o, a), 2, horizon=H, **kw)
    return crossed, dense


# ---------------------------------------------------------------------- the rows
@FAST
@given(n=st.integers(1, 300), m=st.integers(1, 6), A=st.integers(1, 3),
       k=st.integers(1, 3), weighted=st.booleans(), f32=st.booleans(),
       seed=st.integers(0, 2**16))
def test_crossed_rows_products_equal_the_dense_rows(n, m, A, k, weighted, f32, seed):
    rng = np.random.default_rng(seed)
    psi = rng.standard_normal((n, m)).astype(np.float32 if f32 else np.float64)
    acts = rng.integers(-1, A, n)  # -1: empty rows
    rows = CrossedRows(psi, acts, A, chunk=int(rng.integers(1, 64)))
    x = cross_rows(psi.astype(float), acts, A)
    w = rng.random(n) if weighted else None
    xw = x if w is None else x * w[:, None]
    y = rng.standard_normal(n)
    Y = rng.standard_normal((n, k))
    np.testing.assert_allclose(rows.rmatmul(y, w), xw.T @ y, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(rows.rmatmul(Y, w), xw.T @ Y, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(rows.gram(w), xw.T @ x, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(rows.colsums(w), xw.sum(axis=0), rtol=1e-12, atol=1e-11)
    np.testing.assert_array_equal(rows.dense(), x)
    np.testing.assert_array_equal(rows.used(), x.any(axis=1))
    nxt = CrossedRows(psi, None, A)
    u = rng.standard_normal(A * m)
    np.testing.assert_allclose(nxt.action_values(u), cross_rows(psi.astype(float), None, A) @ u,
                               rtol=1e-12, atol=1e-11)


@FAST
@given(n=st.integers(2, 200), m=st.integers(1, 5), seed=st.integers(0, 2**16))
def test_crossed_operator_is_the_ridge_regression_of_the_dense_rows(n, m, seed):
    rng = np.random.default_rng(seed)
    psi, acts = rng.random((n, m)), rng.integers(-1, 2, n)
    x = cross_rows(psi, acts, 2)
    E = CrossedRidgeExpectation(CrossedRows(psi, acts, 2), gamma=0.5)
    lam = x.T @ x + 0.5 * np.eye(2 * m)
    y1, y2 = rng.standard_normal(n), rng.standard_normal(n)
    e1, e2, tot = E.pair_with_total_weights(y1, y2)
    np.testing.assert_allclose(e1, np.linalg.solve(lam, x.T @ y1), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(e2, np.linalg.solve(lam, x.T @ y2), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(tot, np.linalg.solve(lam, x.sum(axis=0)), rtol=1e-9, atol=1e-10)
    # explicit rows (the rules that need them) are the dense rows
    np.testing.assert_array_equal(E.phi, x)
    np.testing.assert_allclose(E(y1), e1, rtol=1e-9, atol=1e-10)


@FAST
@given(n=st.integers(1, 200), m=st.integers(1, 5), A=st.integers(1, 3),
       moments=st.sampled_from([2, 3]), group=st.sampled_from([1, 2, 5]),
       extra=st.integers(0, 3), weighted=st.booleans(), f32=st.booleans(),
       batch=st.sampled_from([1, 2, 3, 128]), keep=st.booleans(), seed=st.integers(0, 2**16))
def test_crossed_sorted_blocks_equal_the_sorted_blocks_of_the_dense_rows(
        n, m, A, moments, group, extra, weighted, f32, batch, keep, seed):
    # signed psi, empty rows (-1), ties in the values, extra breakpoints, sample weights,
    # batches of blocks that cut the groups or hold them all, the blocks' sums kept or formed
    # again when refined: the block sums, their |M| bounds, the refined sums and the exact
    # weights of (factor, block) pairs, without forming the rows, equal those of the dense
    # rows' ridge operator
    rng = np.random.default_rng(seed)
    psi = rng.standard_normal((n, m)).astype(np.float32 if f32 else np.float64)
    acts = rng.integers(-1, A, n)
    w = rng.random(n) + 0.1 if weighted else None
    crossed = CrossedRidgeExpectation(CrossedRows(psi, acts, A), gamma=0.7, weights=w)
    dense = CrossedRidgeExpectation(CrossedRows(psi, acts, A), gamma=0.7, weights=w)
    dense.phi  # noqa: B018  (forms the rows: the dense operator's sorted blocks)
    v = rng.integers(0, 6, n) * rng.standard_normal()  # ties
    ex = rng.standard_normal(extra)
    crossed._keep_blocks = keep
    with patch.object(crossed_blocks, "BATCH_BLOCKS", batch):
        a = crossed.sorted_blocks(v, ex, moments, group)
    b = dense.sorted_blocks(v, ex, moments, group)
    assert crossed._dense is None  # the rows were never formed
    tol = {"rtol": 1e-10, "atol": 1e-12}
    np.testing.assert_array_equal(a.alphas, b.alphas)
    assert a.m == b.m
    np.testing.assert_allclose(a.sums, b.sums, **tol)
    np.testing.assert_allclose(a.sabs, b.sabs, **tol)
    rows = rng.integers(0, A * m, 7)
    nfine = -(-a.alphas.size // 16)
    blocks = rng.integers(0, -(-nfine // group), 7)
    for x, y in zip(a.fine(rows, blocks), b.fine(rows, blocks), strict=True):
        np.testing.assert_allclose(x, y, **tol)
    fine = rng.integers(0, nfine, 7)
    np.testing.assert_allclose(a.pairs(rows, fine), b.pairs(rows, fine), **tol)


@FAST
@given(kind=st.sampled_from(["l1", "l2", "elliptical"]), beta=st.sampled_from([0.0, 0.7]),
       known=st.booleans(), seed=st.integers(0, 2**16))
def test_pooled_next_values_equal_the_per_step_definition(kind, beta, known, seed):
    rng = np.random.default_rng(seed)
    n, A, m = 60, 2, 3
    psi = rng.standard_normal((n, m))
    acts = rng.integers(0, A, n)
    E = CrossedRidgeExpectation(CrossedRows(psi, acts, A), gamma=1.0)
    feats = cross_rows(psi, None, A)
    kv = None
    if known:
        kv = np.full((n, A), np.nan)
        kv[rng.random(n) < 0.2] = 0.25
    w = rng.standard_normal(A * m) * 3
    inv, ellip = E.inverse_diagonal(), E.factor.elliptical_factor()
    old = _NextValue(w, kind, beta, inv, ellip, 2.0)(feats, kv, False)
    for rows in (feats, CrossedRows(psi, None, A)):
        values = PooledNextValues(rows, kv, check=False)
        values.set_penalty(kind, beta, inv, ellip)
        v, _ = values(w, 2.0)
        np.testing.assert_allclose(v, old, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------- the dataset
@FAST
@given(K=st.integers(1, 12), H=st.integers(1, 9), offset=st.booleans(), seed=st.integers(0, 2**16))
def test_episode_datasets_in_the_state_layout_hold_the_dense_numbers(K, H, offset, seed):
    rng = np.random.default_rng(seed)
    crossed, dense = _both(_episodes(rng, K), H, reward_offset=0.5 if offset else None)
    assert type(crossed._source.phi).__name__ == "CrossedField"
    for name in ("phi", "rewards", "next_phi", "next_values", "states", "actions",
                 "next_states"):
        np.testing.assert_array_equal(getattr(crossed, name), getattr(dense, name),
                                      err_msg=name)
    assert crossed.reward_range == dense.reward_range
    assert crossed.nonnegative_features == dense.nonnegative_features
    assert crossed.nonnegative_next_features == dense.nonnegative_next_features
    idx = rng.permutation(K)[: max(1, K // 2)]
    for name in ("phi", "next_phi", "next_values"):
        np.testing.assert_array_equal(getattr(crossed.subset(idx), name),
                                      getattr(dense.subset(idx), name))


ESTIMATORS = pooled_or_per_step_estimators()


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("make", ESTIMATORS)
@pytest.mark.parametrize("pooled", [False, True])
def test_fits_on_the_state_layout_equal_fits_on_the_dense_rows(make, pooled):
    rng = np.random.default_rng(3)
    crossed, dense = _both(_episodes(rng, 40, max_len=12), 10, reward_offset=0.5)
    a, b = make(pooled).fit(crossed), make(pooled).fit(dense)
    if pooled:  # other sums of the same numbers
        np.testing.assert_allclose(a.weights_, b.weights_, rtol=1e-10, atol=1e-10)
    else:  # the same chunks of the same rows: the same bits
        np.testing.assert_array_equal(a.weights_, b.weights_)


def _engine(est, data, early_stop):
    """The estimator's pooled engine run, with or without the fixed-point stop."""
    p = est._validate_common(data)
    p.update(est._validate_extra(data))
    return backward_induction(data, est._make_rule(p), beta=p["beta"], gamma=p["gamma"],
                              penalty=p["penalty"], r_max=p["r_max"], time_homogeneous=True,
                              early_stop=early_stop)


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("make", ESTIMATORS[:5])
@pytest.mark.parametrize("layout", [0, 1])
def test_a_pooled_fit_that_stops_at_a_fixed_point_equals_the_full_loop(make, layout):
    rng = np.random.default_rng(5)
    data = _both(_episodes(rng, 60, max_len=30), 40)[layout]
    est = make(True)
    full, stop = _engine(est, data, False), _engine(est, data, True)
    assert full.diagnostics.stopped_at is None
    np.testing.assert_allclose(stop.weights, full.weights, rtol=1e-9, atol=1e-9)


def test_tv_with_lam_below_the_reward_stops_within_a_few_steps_on_a_failure_task():
    # the failure state is absorbing with value 0 and rewards are 1: TV's target
    # 1 + lam 1[survives] is exact after two steps, so the weights stop changing
    rng = np.random.default_rng(0)
    eps = []
    for _ in range(80):
        T = int(rng.integers(5, 30))
        term = np.zeros(T, dtype=bool)
        term[-1] = T < 29
        eps.append({"observations": rng.random((T + 1, 2)), "actions": rng.integers(0, 2, T),
                    "rewards": np.ones(T), "terminations": term,
                    "truncations": ~term & (np.arange(T) == T - 1)})
    data = _both(eps, 30)[0]
    est = R2PVI("tv", lam=0.1, beta=0.0, r_max=1.0, time_homogeneous=True)
    stop, full = _engine(est, data, True), _engine(est, data, False)
    assert stop.diagnostics.stopped_at is not None and stop.diagnostics.stopped_at >= 25
    np.testing.assert_allclose(stop.weights, full.weights, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(stop.gram_inv_diag, full.gram_inv_diag)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_float32_state_features_fit_like_float32_dense_rows():
    rng = np.random.default_rng(9)
    eps = _episodes(rng, 30, max_len=10)
    a, b = _both(eps, 8, dtype="float32")
    assert a.dtype == np.float32
    for pooled in (False, True):
        x = R2PVI("kl", lam=0.5, beta=0.1, r_max=1.0, time_homogeneous=pooled).fit(a)
        y = R2PVI("kl", lam=0.5, beta=0.1, r_max=1.0, time_homogeneous=pooled).fit(b)
        np.testing.assert_allclose(x.weights_, y.weights_, rtol=1e-10, atol=1e-10)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_per_step_fits_on_the_state_layout_report_what_dense_rows_report():
    rng = np.random.default_rng(11)
    crossed, dense = _both(_episodes(rng, 50, max_len=12), 10)
    a = R2PVI("tv", lam=0.3, time_homogeneous=False).fit(crossed).fit_report_
    b = R2PVI("tv", lam=0.3, time_homogeneous=False).fit(dense).fit_report_
    np.testing.assert_array_equal(a.rows, b.rows)
    np.testing.assert_allclose(a.constant_fit, b.constant_fit, rtol=1e-12)
    np.testing.assert_array_equal(a.absorbing, b.absorbing)


@pytest.mark.parametrize("saved", [False, True])
def test_a_subset_of_state_features_holds_one_copy_of_them_and_fits_as_the_dense_subset(
        tmp_path, saved):
    rng = np.random.default_rng(11)
    crossed, dense = _both(_episodes(rng, 30, max_len=9), 8, reward_offset=0.5)
    if saved:
        crossed = OfflineDataset.open(crossed.save(tmp_path / "states"))
    idx = np.array([3, 0, 17, 17, 29, 5])
    sub = crossed[idx]
    src = sub._source
    assert src.phi.psi is src.next.psi  # taken actions and next states share one copy
    assert not np.shares_memory(src.phi.psi, crossed._source.phi.psi)
    est = R2PVI("tv", lam=0.3, beta=0.1, time_homogeneous=True, r_max=2.0)
    a, b = est.fit(sub).weights_, R2PVI(**est.get_params()).fit(dense[idx]).weights_
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)
