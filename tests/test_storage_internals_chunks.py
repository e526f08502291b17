"""Internals of a fit's reads: a step's products accumulated chunk by chunk.

These tests reach into the step source behind a dataset (``OfflineDataset._source``: its
chunk size, its reads, its cached Gram matrices and column sums, its unit-row flag, its
pooled views, its fields) and into the engine's chunked ridge operator
(``ChunkedRidgeExpectation``), because no public API exposes how a fit reads the data. The
truth is brute-force normal equations and the in-memory fit: the chunked operator is the
ridge regression, each step's features are read as few times as the rule needs, ``E(1)``
costs no pass of its own (the column sums ride along, or come from the Gram matrix for rows
on the simplex), Dask products are formed on the workers, pooled steps are views in memory.
That the fits are the same wherever the data lives is tested through the public API in
test_storage_kinds.py; change these tests with the internals.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from storage_helpers import ESTIMATORS, assert_same_fit, dask_and_memory, make_arrays
from test_large_d import _data, _fit

import r2pvi
from r2pvi import R2PVI, OfflineDataset
from r2pvi.algorithms import DRPVI
from r2pvi.engine import ChunkedRidgeExpectation
from r2pvi.sparse import SparseOfflineDataset

EPS = 2.0**-53


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    phi, rewards, nphi, nv = make_arrays(seed=3)
    mem = OfflineDataset.from_features(phi, rewards, nphi, nv)
    return mem, mem.save(tmp_path_factory.mktemp("stream") / "ds")


@settings(max_examples=20, deadline=None)
@given(k=st.integers(1, 40), chunk=st.integers(1, 50), seed=st.integers(0, 2**16),
       weighted=st.booleans(), scale=st.sampled_from([1e-3, 1.0, 1e3]))
def test_chunked_operator_is_the_ridge_regression(k, chunk, seed, weighted, scale):
    """Against the normal equations, with signed features, signed weights (zero mass
    included), ties and extreme scales; registered columns ride along with the first read."""
    rng = np.random.default_rng(seed)
    d, gamma = 4, 0.7
    phi = scale * rng.normal(size=(k, 2, d))
    phi[: k // 2, :, 0] = phi[0, :, 0]  # ties
    src = OfflineDataset.from_features(phi, rng.random((k, 2)), np.abs(phi[:, :, None]),
                                       check_simplex=False)._source
    src.chunk = chunk
    w = rng.uniform(-0.5, 2.0, size=k) if weighted else None
    if weighted:
        w[rng.random(k) < 0.3] = 0.0
    E = ChunkedRidgeExpectation(src, 1, gamma, w)
    x = phi[:, 1]
    xw = x if w is None else x * w[:, None]
    lam = xw.T @ x + gamma * np.eye(d)
    if np.linalg.eigvalsh(lam).min() <= 1e-8 * np.abs(lam).max():
        return  # signed weights can make Lambda indefinite: not a ridge problem
    y = rng.normal(size=k)
    extra = rng.normal(size=(k, 3))
    E.include(extra)
    got = E(y)
    tol = 1e-9 * (1 + np.abs(np.linalg.solve(lam, xw.T @ y)).max())
    np.testing.assert_allclose(got, np.linalg.solve(lam, xw.T @ y), rtol=0, atol=tol)
    np.testing.assert_allclose(E(extra), np.linalg.solve(lam, xw.T @ extra), rtol=1e-8,
                               atol=1e-8 * (1 + np.abs(np.linalg.solve(lam, xw.T @ extra)).max()))
    assert E.passes == 1  # Lambda, y and the registered columns: one read
    np.testing.assert_allclose(E.inverse_diagonal(), np.diag(np.linalg.inv(lam)), rtol=1e-8)


class Reads:
    """Counts whole-step reads (phi_step) and chunked passes over a source's features."""

    def __init__(self, src, monkeypatch):
        self.whole = self.passes = 0
        step, chunks = src.phi_step, src.phi_chunks

        def phi_step(*a, **k):
            self.whole += 1
            return step(*a, **k)

        def phi_chunks(*a, **k):
            self.passes += 1
            return chunks(*a, **k)

        monkeypatch.setattr(src, "phi_step", phi_step)
        monkeypatch.setattr(src, "phi_chunks", phi_chunks)


@pytest.mark.parametrize("name, gram_known, passes", [
    ("TV", True, 1), ("TV", False, 1), ("PEVI", True, 1), ("KL", True, 1)])
def test_each_step_reads_its_features_as_few_times_as_the_rule_needs(
        saved, name, gram_known, passes, monkeypatch, tmp_path):
    """TV, PEVI and KL: one read per step for Lambda, theta (rewards) and the rule's
    regression (KL's one, with E(1) from the column sums); none holds the whole step. chi^2
    and DRPVI read the step whole, once."""
    _, path = saved
    if not gram_known:  # no stored Gram matrices: the fit forms them from the rows
        path = Path(shutil.copytree(path, tmp_path / "ds"))
        mf = json.loads((path / "manifest.json").read_text())
        del mf["files"]["gram"]
        (path / "manifest.json").write_text(json.dumps(mf))
        (path / "gram.npy").unlink()
    ds = OfflineDataset.open(path)
    reads = Reads(ds._source, monkeypatch)
    est = {"TV": lambda: r2pvi.R2PVI("tv", 0.3), "KL": lambda: r2pvi.R2PVI("kl", 0.3),
           "PEVI": lambda: r2pvi.PEVI(beta=0.1)}[name]().fit(ds)
    H = ds.horizon
    # h = H-1 runs no rule: one pass for theta (and Lambda when it is not known)
    assert reads.passes == 1 + passes * (H - 1)
    assert reads.whole == 0
    assert np.isfinite(est.weights_).all()
    for name in ("chi2", "DRPVI"):
        reads.whole = reads.passes = 0
        ESTIMATORS[name]().fit(ds)
        assert reads.whole == H - 1  # the rows a sorted dual needs, once per step with a rule


# ---------------------------------------------------------------- Dask: products on the workers
def test_dask_products_are_summed_on_the_workers(cluster_client):
    """TV, KL and PEVI steps need only ``Lambda`` and ``Phi^T y``: those are formed on the
    workers, so the client never reads the step's features (any read raises here); chi^2
    reads them (explicit rows). Weighted (variance-aware) fits too."""
    ds, mem = dask_and_memory(170)
    field = ds._source.phi

    def no_client_reads(*args, **kwargs):
        raise AssertionError("the step's features were read on the client")

    field.read = field.chunks = no_client_reads
    for name in ("TV", "KL", "PEVI"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(mem))
    va = {"variance_aware": True}
    assert_same_fit(r2pvi.R2PVI("tv", **va).fit(ds), r2pvi.R2PVI("tv", **va).fit(mem))
    with pytest.raises(AssertionError, match="read on the client"):
        ESTIMATORS["chi2"]().fit(ds)


# ---------------------------------------------------------------- KL: E(1) from the column sums
@pytest.mark.parametrize("stored", [True, False])
def test_chunked_kl_step_reads_once_with_or_without_stored_column_sums(tmp_path, stored):
    """The column sums ride along with the first read of a step (or come from the file):
    ``E(1)`` costs no pass of its own; directories without the optional ``phi_sums.npy`` open
    and fit the same numbers, and the sums a fit forms are kept for the next one."""
    import json

    rng = np.random.default_rng(5)
    K, H, d = 300, 4, 5
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    nphi = rng.dirichlet(np.ones(d), size=(K, H, 2))
    mem = OfflineDataset.from_features(phi, rng.random((K, H)), nphi)
    path = mem.save(tmp_path / "ds")
    sums = np.load(path / "phi_sums.npy")
    np.testing.assert_allclose(sums, phi.sum(axis=0), rtol=1e-12)
    if not stored:  # a directory without the optional column sums
        mf = json.loads((path / "manifest.json").read_text())
        del mf["files"]["phi_sums"]
        (path / "manifest.json").write_text(json.dumps(mf))
        (path / "phi_sums.npy").unlink()
    ds = OfflineDataset.open(path)
    ds._source.chunk = 64
    E = ChunkedRidgeExpectation(ds._source, 1, 1.0)
    y = rng.random(K)
    a, b = E.with_total_weights(y)
    assert E.passes == 1
    x = phi[:, 1]
    lam = x.T @ x + np.eye(d)
    np.testing.assert_allclose(a, np.linalg.solve(lam, x.T @ y), rtol=1e-10)
    np.testing.assert_allclose(b, np.linalg.solve(lam, x.T @ np.ones(K)), rtol=1e-10)
    np.testing.assert_allclose(ds._source.phi_sums(1), x.sum(axis=0), rtol=1e-12)
    fit = r2pvi.R2PVI("kl", 0.3).fit(ds)
    np.testing.assert_allclose(fit.weights_, r2pvi.R2PVI("kl", 0.3).fit(mem).weights_,
                               rtol=0, atol=1e-10)
    bad = tmp_path / "bad"
    mem.save(bad)
    np.save(bad / "phi_sums.npy", sums[:, :2])  # the wrong shape
    with pytest.raises(ValueError, match="column sums"):
        OfflineDataset.open(bad)


@pytest.mark.parametrize("weighted", [False, True])
def test_unit_rows_take_the_column_sums_from_the_gram_matrix(weighted):
    """Rows summing to 1 (validated at construction): ``Phi^T W 1 = Phi^T W Phi 1_d``, so the
    chunk loop forms no product with ones; ``E(1)`` and the KL fit agree with the product
    path within the rows' rounding; rows off the simplex (or not checked) keep the product."""
    rng = np.random.default_rng(11)
    K, H, d = 700, 3, 6
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    nphi = rng.dirichlet(np.ones(d), size=(K, H, 2))
    ds = OfflineDataset.from_features(phi, rng.random((K, H)), nphi)
    assert ds._source.unit_rows and ds.subset(np.arange(0, K, 2))._source.unit_rows
    with pytest.warns(r2pvi.SimplexFeatureWarning):
        off = OfflineDataset.from_features(phi * 1.5, rng.random((K, H)), nphi)
    assert not off._source.unit_rows
    unchecked = OfflineDataset.from_features(phi, rng.random((K, H)), nphi, check_simplex=False)
    assert not unchecked._source.unit_rows
    # float32 rows (p, 1 - p) sum to 1 in float32 but not in float64, where the fits are
    p = rng.uniform(size=(K, H)).astype(np.float32)
    rows32 = np.stack([p, 1 - p], axis=-1)
    assert np.abs(rows32.sum(-1, dtype=np.float64) - 1).max() > 1e-9
    f32 = OfflineDataset.from_features(rows32, rng.random((K, H)),
                                       np.repeat(rows32[:, :, None], 2, axis=2), dtype="float32")
    assert not f32._source.unit_rows
    w = rng.uniform(0.2, 3.0, K) if weighted else None
    ds._source.chunk = 128
    products = []
    x = np.ascontiguousarray(phi[:, 1])
    xw = x if w is None else x * w[:, None]
    truth = np.linalg.solve(xw.T @ x + np.eye(d), xw.T @ np.ones(K))
    for unit in (True, False):
        ds._source.unit_rows = unit
        ds._source._sums[:] = ds._source._grams[:] = [None] * H  # nothing cached
        E = ChunkedRidgeExpectation(ds._source, 1, 1.0, weights=w)
        y = rng.random(K)
        a, b = E.with_total_weights(y)
        assert E.passes == 1
        # which path ran: the Gram matrix's row sums, or the products with ones, as the
        # engine accumulates them (chunk by chunk, the same operations: the same bits)
        gram, prods = np.zeros((d, d)), np.zeros(d)
        for s in range(0, K, 128):
            xc = x[s:s + 128]
            gram += (xc if w is None else xc * w[s:s + 128, None]).T @ xc
            prods += (np.ones(len(xc)) if w is None else w[s:s + 128]) @ xc
        assert np.array_equal(E._sums, gram.sum(axis=1) if unit else prods)
        np.testing.assert_allclose(b, truth, rtol=1e-12)
        np.testing.assert_allclose(a, np.linalg.solve(xw.T @ x + np.eye(d), xw.T @ y),
                                   rtol=1e-10)
        products.append(b)
    # the two paths differ (different sums), by rounding only
    assert np.abs(products[0] - products[1]).max() <= 64 * EPS * np.abs(truth).max()
    ds._source.unit_rows = True
    for lam in (0.01, 1.0, 1e3):
        got = r2pvi.R2PVI("kl", lam).fit(ds).weights_
        ds._source.unit_rows = False
        ds._source._sums[:] = [None] * H
        ref = r2pvi.R2PVI("kl", lam).fit(ds).weights_
        ds._source.unit_rows = True
        ds._source._sums[:] = [None] * H
        np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-12)


# ---------------------------------------------------------------- pooled steps
def test_pooled_views_and_stacked_copies_agree(tmp_path):
    """In memory the pooled rows are views of the step-major arrays (no copy); read from a
    dataset directory, or held as sparse rows, they are stacked step by step: the same fit."""
    rng = np.random.default_rng(13)
    phi, rewards, next_phi = _data(rng, 20, 4, 6)
    next_values = np.full(next_phi.shape[:-1], np.nan)
    next_values[:5, 1] = 0.5  # known values travel with their rows
    ds = OfflineDataset.from_features(phi, rewards, next_phi, next_values)
    views = ds._source.pooled_views(3)
    assert views is not None and np.shares_memory(views[0], ds._source.phi.array)
    stacked = ds.save(tmp_path / "ds")
    opened = OfflineDataset.open(stacked)
    assert opened._source.pooled_views(3) is None
    sparse = SparseOfflineDataset.from_rows(
        [sp.csr_matrix(phi[:, h]) for h in range(4)], rewards,
        [sp.csr_matrix(next_phi[:, h].reshape(-1, 6)) for h in range(4)], 2, next_values)
    for make in (lambda: R2PVI("tv", 0.3, beta=0.1), lambda: DRPVI(0.2, beta=0.1)):
        want = _fit(make, ds, time_homogeneous=True).weights_
        for other in (opened, sparse):
            np.testing.assert_allclose(_fit(make, other, time_homogeneous=True).weights_,
                                       want, atol=1e-10)
