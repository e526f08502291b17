"""The streaming engine: a step's Gram matrix and regressions accumulated by chunk.

The truth is the engine's full path (the step's (K, d) features in memory, one Gram product,
the ridge operator of :mod:`r2pvi.duals.operator`) and brute-force normal equations; the
chunked path must give the same fits to 1e-10, read each step's features as few times as
the rule allows, and never hold a step's (K, d) features for TV, KL and PEVI.
"""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_storage import ESTIMATORS, assert_same_fit, make_arrays

import r2pvi
from r2pvi import OfflineDataset, engine
from r2pvi.engine import ChunkedRidgeExpectation


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    phi, rewards, nphi, nv = make_arrays(seed=3)
    mem = OfflineDataset.from_features(phi, rewards, nphi, nv)
    return mem, mem.save(tmp_path_factory.mktemp("stream") / "ds")


def full_path_fit(name, ds, monkeypatch):
    """The fit with each step's (K, d) features in memory (the engine's unchunked path)."""
    with monkeypatch.context() as m:
        m.setattr(engine.induction, "_streams", lambda *a: False)
        return ESTIMATORS[name]().fit(ds)


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_chunked_fit_equals_the_in_memory_full_path(saved, name, monkeypatch):
    mem, path = saved
    ref = full_path_fit(name, mem, monkeypatch)
    ds = OfflineDataset.open(path)
    ds._source.chunk = 61
    assert_same_fit(ESTIMATORS[name]().fit(ds), ref)
    # again, now from the Gram matrices the first fit (or the file) left in the cache
    assert_same_fit(ESTIMATORS[name]().fit(ds), ref)


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
        saved, name, gram_known, passes, monkeypatch):
    """TV, PEVI and KL: one read per step for Lambda, theta (rewards) and the rule's
    regression (KL's one, with E(1) from the column sums); none holds the whole step. chi^2
    and DRPVI read the step whole, once."""
    _, path = saved
    ds = OfflineDataset.open(path)
    if not gram_known:
        ds._source._grams = [None] * ds.horizon
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


def test_gram_matrices_are_stored_with_the_data_and_checked(saved, tmp_path):
    mem, path = saved
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["files"]["gram"] == "gram.npy"
    grams = np.load(path / "gram.npy")
    phi = mem.phi
    for h in range(mem.horizon):
        np.testing.assert_allclose(grams[h], phi[:, h].T @ phi[:, h], rtol=1e-12)
    # float32 storage: the Gram matrices are those of the rounded features that are stored
    f32 = mem.save(tmp_path / "f32", dtype="float32")
    x = OfflineDataset.open(f32).phi[:, 0].astype(np.float64)
    np.testing.assert_allclose(np.load(f32 / "gram.npy")[0], x.T @ x, rtol=1e-12)
    np.save(f32 / "gram.npy", grams[:, :2])  # the wrong shape
    with pytest.raises(ValueError, match="Gram matrices"):
        OfflineDataset.open(f32)


def test_streamed_fits_never_hold_a_step(tmp_path):
    """Peak traced memory of a TV fit from disk stays far below one step's (K, d) float64
    features; the chi^2 fit (exact, sorted) holds them, which shows the measure can fail."""
    K, H, d, A = 4000, 3, 48, 2
    rng = np.random.default_rng(1)
    phi = rng.dirichlet(np.ones(d), size=(K, H)).astype(np.float32)
    nphi = rng.dirichlet(np.ones(d), size=(K, H, A)).astype(np.float32)
    path = OfflineDataset.from_features(phi, rng.random((K, H)), nphi).save(tmp_path / "m")
    step_bytes = K * d * 8
    peaks = {}
    for name in ("TV", "chi2"):
        ds = OfflineDataset.open(path)
        ds._source.chunk = 64
        ESTIMATORS[name]().fit(ds)  # imports, caches, the reader thread
        tracemalloc.start()
        try:
            ESTIMATORS[name]().fit(ds)
            peaks[name] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peaks["TV"] < 0.4 * step_bytes, peaks
    assert peaks["chi2"] > step_bytes, peaks
