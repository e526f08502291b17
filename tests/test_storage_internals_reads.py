"""Internals of reading stored files chunk by chunk: mapped windows, the pread fallback, and
next-state values as one matrix-vector product per chunk.

These tests reach into the storage's file reads (``storage.files._prefetched``, ``_unmap``,
``MAP_WINDOW``, ``FileField``) and the engine's next-state values (``engine._q_step``,
``_max_over_actions``, ``_NextValue``), because no public API exposes how a step is read.
The truth is the unchunked definition (``_q_step`` on the whole step, ``FileField.read``)
and the in-memory fit; change these tests with the internals.
"""

from __future__ import annotations

import mmap

import numpy as np
import pytest

import r2pvi
from r2pvi import OfflineDataset, engine
from r2pvi.data.storage import files
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


def test_float32_files_are_read_by_pread_and_cast(data, monkeypatch):
    """float32 files: no map; every chunk is float64, equal to FileField.read, in file order,
    in one reused buffer; and the fits equal the in-memory fit."""
    mem, path = data
    f = FileField(path / "next_phi.npy")
    assert f.dtype == np.float32

    def refuse(*a, **k):
        raise AssertionError("float32 files are not mapped")

    monkeypatch.setattr(mmap, "mmap", refuse)
    H, K = f.shape[:2]
    for chunk in (4096, 64, 7):
        shape = (min(chunk, K),) + f.shape[2:]
        for h in (0, H - 1):
            seen, buffers = 0, set()
            for s, e, rows in files._prefetched(f, h, K, chunk, shape):
                assert s == seen and rows.dtype == np.float64 and rows.flags.c_contiguous
                np.testing.assert_array_equal(rows, f.read(h, s, e))
                buffers.add(rows.__array_interface__["data"][0])
                seen = e
            assert seen == K and len(buffers) == 1
    f.close()
    for a, b in zip(fits(OfflineDataset.open(path)), fits(mem), strict=True):
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
        raw = engine.q._max_over_actions(engine.q._q_step(feats[1], w, penalty, beta, inv_diag,
                                                      ellip, np.inf, None, not signed))
        if (raw < 0).sum() > 5 and (raw > 0).sum() > 20:
            break
    upper = float(np.quantile(raw[raw > 0], 0.7))
    qmax = engine.q._NextValue(w, penalty, beta, inv_diag, ellip, upper)
    truth = engine.q._max_over_actions(engine.q._q_step(feats[1], w, penalty, beta, inv_diag,
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


# ----------------------------------------------------------------------------- float64 files
@pytest.fixture(scope="module")
def data64(data, tmp_path_factory):
    mem, _ = data
    return mem, mem.save(tmp_path_factory.mktemp("reads64") / "ds", dtype="float64")


def _mapping(rows):
    """The ``mmap`` an array is a view of (through NumPy's memoryview), else None."""
    base = rows
    while base is not None and not isinstance(base, memoryview):
        base = base.base
    return None if base is None else base.obj


@pytest.mark.parametrize("window, chunk", [(1 << 25, 4096), (4096, 64), (100, 7)])
def test_float64_files_are_read_as_views_of_the_map(data64, window, chunk, monkeypatch):
    """Native float64 files: every chunk is a read-only view of the mapped window (no copy),
    bitwise what pread reads, in file order; windows smaller than a step, chunks that straddle
    nothing or everything."""
    _, path = data64
    # the module that reads MAP_WINDOW (the package re-exports only its value)
    monkeypatch.setattr(files, "MAP_WINDOW", window)
    maps = []
    real = mmap.mmap

    def counted(*a, **k):
        maps.append(a[1])
        return real(*a, **k)

    monkeypatch.setattr(mmap, "mmap", counted)
    for name in ("phi.npy", "next_phi.npy"):
        f = FileField(path / name)
        assert f.dtype == np.float64
        H, K = f.shape[:2]
        shape = (min(chunk, K),) + f.shape[2:]
        for h in (0, H - 1):
            seen = 0
            maps.clear()
            for s, e, rows in files._prefetched(f, h, K, chunk, shape):
                assert s == seen and rows.shape == (e - s,) + f.shape[2:]
                assert rows.dtype == np.float64 and rows.flags.c_contiguous
                assert not rows.flags.writeable and not rows.flags.owndata
                assert isinstance(_mapping(rows), real)
                assert rows.tobytes() == f.read(h, s, e).tobytes()
                seen = e
            assert seen == K
            # the window took effect: a step is mapped whole only when it fits in one window
            step = K * f._row
            assert (len(maps) == 1) == (step <= window), (len(maps), step, window)
        f.close()


def test_a_kept_float64_chunk_stays_valid_and_its_map_goes_with_it(data64, monkeypatch):
    """A chunk kept past its iteration (against the contract) never points at unmapped memory:
    closing its window is refused (BufferError, caught), the window stays mapped while a view
    lives and is unmapped when the last view goes (the mmap is deallocated). A pass keeps at
    most two windows alive (the caller's loop variable holds the previous chunk while the next
    window is mapped), so the resident memory stays bounded."""
    import gc
    import weakref

    _, path = data64
    monkeypatch.setattr(files, "MAP_WINDOW", 4096)
    f = FileField(path / "next_phi.npy")
    K = f.shape[1]
    shape = (64,) + f.shape[2:]

    def alive(refs):
        return [r() for r in refs if r() is not None and not r().closed]

    refs, kept = [], None
    for s, e, rows in files._prefetched(f, 1, K, 64, shape):  # run to the end
        mm = _mapping(rows)
        if not refs or refs[-1]() is not mm:
            refs.append(weakref.ref(mm))
        del mm
        assert len(alive(refs)) <= 2 + (kept is not None)
        if s == 64:
            kept = (s, e, rows)
    assert len(refs) > 2
    del rows
    s, e, rows = kept
    del kept
    mine = _mapping(rows)
    assert alive(refs) == [mine]  # every other window is unmapped
    np.testing.assert_array_equal(rows, f.read(1, s, e))
    assert files._unmap(mine) is False and not mine.closed  # a view is alive
    # abandoned half-way while a chunk is held: no BufferError from the generator's close
    gen = files._prefetched(f, 1, K, 64, shape)
    s2, e2, held = next(gen)
    gen.close()
    np.testing.assert_array_equal(held, f.read(1, s2, e2))
    assert not _mapping(held).closed
    gone = weakref.ref(_mapping(held))
    del held
    assert gone() is None
    # the last view released: nothing exports the map any more
    del rows
    gc.collect()
    assert files._unmap(mine) is True and mine.closed
    f.close()


def test_float64_fits_without_a_copy_equal_the_copying_reads(data64, monkeypatch):
    """The zero-copy path does the arithmetic of the copying one (pread into a float64
    buffer): the same weights bitwise; and the in-memory fit's to 1e-10."""
    mem, path = data64
    direct = fits(OfflineDataset.open(path))

    def refuse(*a, **k):
        raise OSError("no mmap here")

    with monkeypatch.context() as m:
        m.setattr(mmap, "mmap", refuse)
        copied = fits(OfflineDataset.open(path))
    for a, b, c in zip(direct, copied, fits(mem), strict=True):
        assert a.tobytes() == b.tobytes()
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-10)


def test_unaligned_float64_files_are_copied(tmp_path):
    """A float64 .npy whose data starts off an 8-byte boundary (a hand-made header): the
    chunks are copied into an aligned buffer, equal to what pread reads."""
    rng = np.random.default_rng(5)
    a = rng.random((2, 50, 3))
    text = repr({"descr": "<f8", "fortran_order": False, "shape": a.shape})
    pad = (-(10 + len(text) + 1)) % 64 + 4  # magic, length, text, pad, newline: 4 mod 64
    blob = text + " " * pad + "\n"
    path = tmp_path / "odd.npy"
    with open(path, "wb") as fh:
        fh.write(np.lib.format.magic(1, 0) + len(blob).to_bytes(2, "little") + blob.encode())
        fh.write(a.tobytes())
    f = FileField(path)
    assert f.offset % 8 == 4 and f.dtype == np.float64
    for s, e, rows in files._prefetched(f, 1, 50, 16, (16, 3)):
        assert rows.flags.aligned and rows.flags.writeable
        np.testing.assert_array_equal(rows, a[1, s:e])
    f.close()
