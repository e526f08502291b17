"""The streaming read path: mapped windows, the pread fallback, and next-state values as one
matrix-vector product per chunk. The truth is the unchunked definition (``_q_step`` on the
whole step, ``FileField.read``) and the in-memory fit."""

from __future__ import annotations

import mmap

import numpy as np
import pytest

import r2pvi
from r2pvi import OfflineDataset, engine, storage
from r2pvi.storage import ArrayField, FileField, StoredNext


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    rng = np.random.default_rng(11)
    K, H, d, A = 700, 4, 5, 2
    phi = rng.dirichlet(np.ones(d), size=(K, H)).astype(np.float32)
    nphi = rng.dirichlet(np.ones(d), size=(K, H, A)).astype(np.float32)
    mem = OfflineDataset.from_features(phi, rng.random((K, H)), nphi)
    return mem, mem.save(tmp_path_factory.mktemp("reads") / "ds")


def fits(ds):
    return [est.fit(ds).weights_ for est in (r2pvi.R2PVI("tv", 0.3), r2pvi.R2PVI("kl", 0.3),
                                              r2pvi.PEVI(beta=0.1))]


@pytest.mark.parametrize("window, chunk", [(1 << 25, 4096), (4096, 64), (100, 7)])
def test_mapped_windows_read_what_pread_reads(data, window, chunk, monkeypatch):
    """Windows smaller than a step, chunks that straddle nothing or everything: every chunk
    equals FileField.read (pread), float64 and in file order."""
    _, path = data
    f = FileField(path / "next_phi.npy")
    monkeypatch.setattr(storage, "MAP_WINDOW", window)
    H, K = f.shape[:2]
    shape = (min(chunk, K),) + f.shape[2:]
    for h in (0, H - 1):
        seen = 0
        for s, e, rows in storage._prefetched(f, h, K, chunk, shape):
            assert s == seen and rows.dtype == np.float64
            np.testing.assert_array_equal(rows, f.read(h, s, e))
            seen = e
        assert seen == K
    # a pass abandoned half-way releases its map (no BufferError, no open map left behind)
    gen = storage._prefetched(f, 1, K, chunk, shape)
    next(gen)
    gen.close()


def test_unmappable_files_fall_back_to_pread_with_the_same_fits(data, monkeypatch):
    mem, path = data
    ref = fits(mem)

    def refuse(*a, **k):
        raise OSError("no mmap here")

    monkeypatch.setattr(mmap, "mmap", refuse)
    got = fits(OfflineDataset.open(path))
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)


@pytest.mark.parametrize("penalty", ["l1", "l2", "elliptical"])
@pytest.mark.parametrize("beta", [0.0, 0.7])
@pytest.mark.parametrize("A, signed", [(1, False), (2, False), (3, False), (2, True)])
def test_next_state_values_by_one_product_equal_the_definition(penalty, beta, A, signed):
    """``V = clip(max_a phi_a^T u, 0, upper)`` (one product per chunk, one clip) where Q is
    linear, the engine's ``max_a Q`` on each chunk otherwise: both equal ``_q_step`` on the
    whole step (the definition), with values at and beyond both ends of the clip."""
    n, d = 333, 4
    ellip = (np.linalg.cholesky(np.eye(d) + 0.1), 0.0, 1.0) if penalty == "elliptical" else None
    for seed in range(100):  # data whose values fall below 0, inside and above the clip
        rng = np.random.default_rng(seed)
        feats = rng.normal(size=(2, n, A, d)) if signed else rng.random((2, n, A, d))
        w = rng.normal(size=d) * 3.0
        inv_diag = rng.random(d)
        raw = engine._max_over_actions(engine._q_step(feats[1], w, penalty, beta, inv_diag,
                                                      ellip, np.inf, None, not signed))
        if (raw < 0).sum() > 5 and (raw > 0).sum() > 20:
            break
    upper = float(np.quantile(raw[raw > 0], 0.7))
    qmax = engine._NextValue(w, penalty, beta, inv_diag, ellip, upper)
    truth = engine._max_over_actions(engine._q_step(feats[1], w, penalty, beta, inv_diag,
                                                    ellip, upper, None, not signed))
    assert (truth == 0.0).any() and (truth == upper).any()
    assert ((truth > 0) & (truth < upper)).any()
    nxt = StoredNext(ArrayField(feats), None, not signed)
    got = nxt.values(1, qmax, n, 50)
    np.testing.assert_array_equal(got, truth)
    out = np.full(n, np.nan)
    assert nxt.values(1, qmax, n, 50, out=out) is out
    np.testing.assert_array_equal(out, truth)
    linear = qmax.linear(not signed)
    assert (linear is not None) == (beta == 0.0 or (penalty == "l1" and not signed))
