"""Step-major storage: the on-disk format, the writer, computed next states, streaming fits.

The truth for every streamed fit is the in-memory fit of the same numbers: the engine's
results must not depend on where the data lives or how a step is cut into chunks.
"""

from __future__ import annotations

import json
import os
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import DatasetWriter, OfflineDataset
from r2pvi.algorithms import DRPVI, DRVIL
from r2pvi.data.storage import CHUNK
from r2pvi.envs import FiniteLinearMDP

K, H, D, A = 600, 4, 5, 3  # K >= 512: chi^2 takes its blockwise (branch and bound) path


def make_arrays(k=K, seed=0, known=True):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), size=(k, H))
    nphi = rng.dirichlet(np.ones(D), size=(k, H, A))
    rewards = phi @ rng.uniform(0, 1, D)
    nv = None
    if known:
        nv = np.full((k, H, A), np.nan)
        nv[rng.random((k, H)) < 0.2, 0] = 0.0  # a known-value action (an exercise, a fail)
    return phi, rewards, nphi, nv


ESTIMATORS = {
    "PEVI": lambda: r2pvi.PEVI(beta=0.1),
    "TV": lambda: r2pvi.R2PVI("tv", 0.3, beta=0.1),
    "KL": lambda: r2pvi.R2PVI("kl", 0.3, beta=0.1),
    "chi2": lambda: r2pvi.R2PVI("chi2", 0.3, beta=0.1),
    "DRPVI": lambda: DRPVI(0.2, beta=0.1),
    "DRVI-L": lambda: DRVIL(0.2, beta=0.1),
    "VA-TV": lambda: r2pvi.R2PVI("tv", 0.3, beta=0.1, variance_aware=True),
}


def assert_same_fit(a, b, atol=1e-10):
    for name in ("weights_", "reward_weights_", "gram_inv_diag_"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol,
                                   err_msg=name)
    if getattr(a, "_elliptical", None) is not None:  # the elliptical penalty's fitted factors
        for (ra, *ca), (rb, *cb) in zip(a._elliptical, b._elliptical, strict=True):
            np.testing.assert_allclose(ra, rb, rtol=0, atol=atol, err_msg="elliptical")
            assert ca == cb


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The same numbers in memory, as a saved directory and written by chunks."""
    phi, rewards, nphi, nv = make_arrays()
    mem = OfflineDataset.from_features(phi, rewards, nphi, nv)
    root = tmp_path_factory.mktemp("storage")
    saved = mem.save(root / "saved")
    with DatasetWriter(root / "written", horizon=H, n_features=D, n_actions=A,
                       dtype="float64") as w:
        for s, e in ((0, 1), (1, 250), (250, 251), (251, K)):  # uneven chunks
            w.append(phi[s:e], rewards[s:e], nphi[s:e], nv[s:e])
    return mem, saved, root / "written"


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_fit_is_the_same_in_memory_on_disk_and_in_any_chunking(stored, name):
    mem, saved, written = stored
    ref = ESTIMATORS[name]().fit(mem)
    for ds in (OfflineDataset.open(saved), OfflineDataset.open(written)):
        assert ds.storage == "disk"
        ds._source.chunk = 97  # force many chunks per step
        assert_same_fit(ESTIMATORS[name]().fit(ds), ref)
    mem._source.chunk = 1
    try:
        assert_same_fit(ESTIMATORS[name]().fit(mem), ref)
    finally:
        mem._source.chunk = CHUNK


@settings(max_examples=15, deadline=None)
@given(chunk=st.integers(1, 80), k=st.integers(1, 60), seed=st.integers(0, 2**16))
def test_next_state_values_do_not_depend_on_the_chunking(chunk, k, seed):
    phi, rewards, nphi, nv = make_arrays(k, seed)
    ds = OfflineDataset.from_features(phi, rewards, nphi, nv, check_simplex=False)
    ref = r2pvi.R2PVI("kl", 0.5, beta=0.05).fit(ds)
    ds._source.chunk = chunk
    assert_same_fit(r2pvi.R2PVI("kl", 0.5, beta=0.05).fit(ds), ref)


def test_directory_format_is_documented_step_major_and_lazy(stored):
    mem, saved, written = stored
    manifest = json.loads((saved / "manifest.json").read_text())
    assert manifest["kind"] == "r2pvi.OfflineDataset" and manifest["format_version"] == 2
    assert manifest["layout"] == "step-major" and manifest["next"] == "stored"
    raw = np.load(saved / "phi.npy", allow_pickle=False)
    assert raw.shape == (H, K, D)
    np.testing.assert_array_equal(raw, mem.phi.transpose(1, 0, 2))
    ds = OfflineDataset.open(written)
    assert isinstance(ds.phi.base, np.memmap) or isinstance(ds.phi, np.memmap)
    for name in ("phi", "rewards", "next_values"):
        np.testing.assert_array_equal(getattr(ds, name), getattr(mem, name))
    np.testing.assert_array_equal(ds.next_phi[:, : H - 1], mem.next_phi[:, : H - 1])
    assert ds.nonnegative_features and ds.nonnegative_next_features
    sub = ds.subset([3, 1])
    assert sub.storage == "memory"
    np.testing.assert_array_equal(sub.phi, mem.phi[[3, 1]])


def test_open_rejects_foreign_future_missing_and_truncated(tmp_path):
    ds = OfflineDataset.from_features(*make_arrays(20)[:3])
    path = ds.save(tmp_path / "d")
    with pytest.raises(FileNotFoundError):
        OfflineDataset.open(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no manifest.json"):
        OfflineDataset.open(tmp_path / "empty")
    mf = json.loads((path / "manifest.json").read_text())
    (path / "manifest.json").write_text(json.dumps({**mf, "format_version": 99}))
    with pytest.raises(ValueError, match="format version 99"):
        OfflineDataset.open(path)
    (path / "manifest.json").write_text(json.dumps(mf))
    with open(path / "phi.npy", "r+b") as fh:
        fh.truncate(os.path.getsize(path / "phi.npy") - 8)
    with pytest.raises(ValueError, match="truncated"):
        OfflineDataset.open(path)
    with pytest.raises(FileExistsError):
        ds.save(path)
    ds.save(path, overwrite=True)
    assert OfflineDataset.open(path).n_trajectories == 20


def test_writer_validates_each_chunk_and_is_atomic(tmp_path):
    phi, rewards, nphi, nv = make_arrays(30)
    target = tmp_path / "w"
    w = DatasetWriter(target, horizon=H, n_features=D, n_actions=A)
    w.append(phi[:10], rewards[:10], nphi[:10])
    bad = phi[10:20].copy()
    bad[3, 1, 2] = np.nan
    with pytest.raises(ValueError, match="phi contains 1 NaN"):
        w.append(bad, rewards[10:20], nphi[10:20])
    with pytest.raises(ValueError, match=r"next_phi must have shape \(k, H, A, d\)"):
        w.append(phi[10:20], rewards[10:20], nphi[10:20, :, :2])
    with pytest.raises(ValueError, match="rewards must have shape"):
        w.append(phi[10:20], rewards[:3], nphi[10:20])
    with pytest.raises(TypeError, match="phi must be a numeric"):
        w.append(phi.astype(object), rewards, nphi)
    assert not target.exists()  # nothing at the path before close
    w.append(phi[10:], rewards[10:], nphi[10:], nv[10:])  # next_values in one chunk only
    assert w.close() == target
    ds = OfflineDataset.open(target)
    assert ds.dtype == np.float32 and ds.has_known_values
    assert np.isnan(ds.next_values[:10]).all()
    np.testing.assert_array_equal(ds.next_values[10:, : H - 1], nv[10:, : H - 1])
    np.testing.assert_array_equal(ds.phi, phi.astype(np.float32))
    with pytest.raises(RuntimeError, match="closed"):
        w.append(phi, rewards, nphi)
    with pytest.raises(FileExistsError):
        DatasetWriter(target, horizon=H, n_features=D, n_actions=A)
    with pytest.raises(RuntimeError, match="boom"):  # an error inside `with` discards all
        with DatasetWriter(tmp_path / "x", horizon=H, n_features=D, n_actions=A) as w2:
            w2.append(phi, rewards, nphi)
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]  # no temporary left behind
    with pytest.raises(ValueError, match="no trajectories"):
        DatasetWriter(tmp_path / "e", horizon=H, n_features=D, n_actions=A).close()
    with pytest.raises(ValueError, match="dtype"):
        DatasetWriter(tmp_path / "f", horizon=H, n_features=D, n_actions=A, dtype="int8")
    with pytest.raises(ValueError, match="dtype"):
        DatasetWriter(tmp_path / "g", horizon=H, n_features=D, n_actions=A, dtype="bogus")


def test_writer_warns_once_off_the_simplex(tmp_path):
    phi, rewards, nphi, _ = make_arrays(10)
    with DatasetWriter(tmp_path / "s", horizon=H, n_features=D, n_actions=A) as w:
        for _ in range(3):
            w.append(2 * phi, rewards, nphi)
        with pytest.warns(r2pvi.SimplexFeatureWarning) as record:
            w.close()
    assert len(record) == 1


def test_from_features_copies_at_most_once_and_never_for_step_major_floats():
    rng = np.random.default_rng(0)
    k, h, d, a = 4000, 5, 10, 2
    sm_phi = rng.dirichlet(np.ones(d), size=(h, k))  # step-major (H, K, d)
    sm_next = rng.dirichlet(np.ones(d), size=(h, k, a))
    sm_r = rng.random((h, k))
    nbytes = sm_phi.nbytes + sm_next.nbytes + sm_r.nbytes
    args = (sm_phi.transpose(1, 0, 2), sm_r.T, sm_next.transpose(1, 0, 2, 3))
    tracemalloc.start()
    try:
        ds = OfflineDataset.from_features(*args)
        zero_copy_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        traj_major = [np.ascontiguousarray(x) for x in args]  # the usual (K, H, ...) layout
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        ds2 = OfflineDataset.from_features(*traj_major)
        one_copy_peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert np.shares_memory(ds.phi, sm_phi) and np.shares_memory(ds.next_phi, sm_next)
    assert zero_copy_peak < 0.1 * nbytes
    assert not np.shares_memory(ds2.phi, traj_major[0])
    assert one_copy_peak < 1.2 * nbytes  # one step-major copy, chunked validation
    assert sm_phi.flags.writeable  # the caller's array is left as it was
    assert_same_fit(r2pvi.R2PVI("tv", 0.5).fit(ds), r2pvi.R2PVI("tv", 0.5).fit(ds2), 0)


def test_float32_storage_accumulates_in_float64(tmp_path):
    phi, rewards, nphi, nv = make_arrays()
    ref = OfflineDataset.from_features(phi, rewards, nphi, nv)
    f32 = OfflineDataset.from_features(phi, rewards, nphi, nv, dtype="float32")
    assert f32.dtype == np.float32 and f32.phi.dtype == np.float32
    on_disk = OfflineDataset.open(ref.save(tmp_path / "f32", dtype="float32"))
    for name in ("TV", "KL", "chi2", "DRPVI"):
        a = ESTIMATORS[name]().fit(ref)
        b = ESTIMATORS[name]().fit(f32)
        # only the inputs are rounded (to 6e-8 relative): the fits stay within 1e-6
        np.testing.assert_allclose(b.weights_, a.weights_, rtol=0, atol=1e-6, err_msg=name)
        assert_same_fit(ESTIMATORS[name]().fit(on_disk), b)
    # numbers that are float32 already lose nothing: identical to the float64 fit
    exact = OfflineDataset.from_features(phi.astype(np.float32).astype(float), rewards,
                                         nphi.astype(np.float32).astype(float), nv)
    assert_same_fit(ESTIMATORS["chi2"]().fit(exact), ESTIMATORS["chi2"]().fit(f32))


def test_finite_mdp_datasets_index_a_feature_table_and_fit_the_same():
    rng = np.random.default_rng(3)
    S, Am, d, h = 6, 2, 3, 4
    feats = rng.dirichlet(np.ones(d), size=(h, S, Am))
    feats[:, 0] = np.eye(d)[0]  # state 0 is an absorbing fail state
    mu = rng.dirichlet(np.ones(S), size=(h, d))
    mu[:, 0] = np.eye(S)[0]
    theta = rng.uniform(0, 1, (h, d))
    theta[:, 0] = 0.0
    env = FiniteLinearMDP(feats, theta, mu, initial=1, fail_states=[0])
    ds = env.collect(300, seed=1)
    assert ds.n_trajectories == 300 and ds.has_known_values
    dense = OfflineDataset.from_features(ds.phi, ds.rewards, ds.next_phi, ds.next_values)
    np.testing.assert_array_equal(ds.next_phi[:, :-1], feats[1:][np.arange(h - 1),
                                                                 ds.next_states[:, :-1]])
    for name in ("TV", "chi2", "DRPVI"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(dense))
        small = ds.subset(np.arange(4))  # fewer samples than states: gathered features
        assert_same_fit(ESTIMATORS[name]().fit(small), ESTIMATORS[name]().fit(
            OfflineDataset.from_features(small.phi, small.rewards, small.next_phi,
                                         small.next_values)))


def test_table_dataset_round_trips_through_the_directory_format(tmp_path):
    table = np.random.default_rng(0).dirichlet(np.ones(3), size=(5, 2))
    idx = np.random.default_rng(1).integers(5, size=(40, 3))
    act = np.random.default_rng(2).integers(2, size=(40, 3))
    known = np.full((5, 2), np.nan)
    known[4] = 0.0
    ds = OfflineDataset.from_next_state_table(table[idx, act], idx[:, ::-1] * 0.1, idx, table,
                                              known, actions=act)
    back = OfflineDataset.open(ds.save(tmp_path / "t"))
    assert json.loads((tmp_path / "t" / "manifest.json").read_text())["next"] == "table"
    assert not (tmp_path / "t" / "next_phi.npy").exists()  # nothing per sample but an index
    np.testing.assert_array_equal(back.actions, act)
    assert_same_fit(ESTIMATORS["KL"]().fit(back), ESTIMATORS["KL"]().fit(ds))
    with pytest.raises(ValueError, match=r"next_states must lie in \[0, 5\)"):
        OfflineDataset.from_next_state_table(table[idx, act], idx * 0.1, idx + 1, table)
    with pytest.raises(ValueError, match="known_values must have shape"):
        OfflineDataset.from_next_state_table(table[idx, act], idx * 0.1, idx, table, known[:2])


def test_feature_map_next_states_are_computed_chunk_by_chunk(tmp_path):
    rng = np.random.default_rng(4)
    centers = np.linspace(0, 1, D)

    def fmap(x, a):  # normalized RBF on a 1-D observation, shifted by the action
        z = np.exp(-((x[:, :1] + 0.1 * a[:, None] - centers) ** 2) / 0.05)
        return z / z.sum(axis=1, keepdims=True)

    k = 700
    obs, nxt = rng.random((k, H, 1)), rng.random((k, H, 1))
    act = rng.integers(A, size=(k, H))
    rewards = obs[..., 0]

    def exercise(o):  # action 0 stops with a known payoff above 0.8
        out = np.full((o.shape[0], A), np.nan)
        out[:, 0] = np.where(o[:, 0] > 0.8, o[:, 0], np.nan)
        return out

    ds = OfflineDataset.from_observations(obs, act, rewards, nxt, fmap, A, exercise)
    ds._source.chunk = 64
    dense = OfflineDataset.from_transitions(obs, act, rewards, nxt, fmap, A, exercise)
    np.testing.assert_allclose(ds.phi, dense.phi, rtol=0, atol=1e-15)
    assert ds.has_known_values and not np.isnan(ds.next_values[:, 0, 0]).all()
    for name in ("TV", "KL", "chi2"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(dense))
    path = ds.save(tmp_path / "m")  # the observations are stored, not the features
    assert not (path / "phi.npy").exists() and not (path / "next_phi.npy").exists()
    with pytest.raises(ValueError, match="pass the feature_map"):
        OfflineDataset.open(path)
    saved = OfflineDataset.open(path, feature_map=fmap)
    saved._source.chunk = 100
    assert_same_fit(ESTIMATORS["TV"]().fit(saved), ESTIMATORS["TV"]().fit(dense))
    assert_same_fit(ESTIMATORS["TV"]().fit(saved.subset([5, 2, 9])),
                    ESTIMATORS["TV"]().fit(dense.subset([5, 2, 9])))
    with pytest.raises(ValueError, match=r"actions must lie in \[0, 3\)"):
        OfflineDataset.from_observations(obs, act + 1, rewards, nxt, fmap, A)


@pytest.fixture(scope="module")
def cluster_client():
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                       dashboard_address=None)
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


def dask_and_memory(chunk):
    """The same data as Dask arrays (``chunk`` trajectories per block) and in memory."""
    da = pytest.importorskip("dask.array")
    arrays = make_arrays()
    ds = OfflineDataset.from_dask(*(da.from_array(a, chunks=(chunk,) + (-1,) * (a.ndim - 1))
                                    for a in arrays))
    return ds, OfflineDataset.from_features(*arrays)


def test_dask_arrays_on_a_local_cluster_fit_as_in_memory(cluster_client):
    ds, mem = dask_and_memory(250)
    phi, rewards, nphi, _ = make_arrays()
    assert ds.storage == "dask" and ds.n_trajectories == K
    for name in ("TV", "chi2"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(mem))
    with pytest.raises(TypeError, match="dask.array"):
        OfflineDataset.from_dask(phi, rewards, nphi)


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


def test_actions_with_known_values_need_no_features(tmp_path):
    phi, rewards, nphi, nv = make_arrays(200, seed=5)
    holes = nphi.copy()
    holes[~np.isnan(nv)] = np.nan  # no features where the value is known
    ref = OfflineDataset.from_features(phi, rewards, nphi, nv)
    ds = OfflineDataset.from_features(phi, rewards, holes, nv)
    assert ds.nonnegative_next_features
    with DatasetWriter(tmp_path / "k", horizon=H, n_features=D, n_actions=A,
                       dtype="float64") as w:
        w.append(phi, rewards, holes, nv)
    for name in ("TV", "chi2", "PEVI"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(ref))
        assert_same_fit(ESTIMATORS[name]().fit(OfflineDataset.open(tmp_path / "k")),
                        ESTIMATORS[name]().fit(ref))
    holes[0, 0, 1] = np.nan  # a learned action still needs its features
    with pytest.raises(ValueError, match="where no value is known"):
        OfflineDataset.from_features(phi, rewards, holes, nv)


def test_a_dropped_writer_leaves_nothing_behind(tmp_path):
    import gc

    w = DatasetWriter(tmp_path / "gone", horizon=H, n_features=D, n_actions=A)
    w.append(*make_arrays(5)[:3])
    assert len(list(tmp_path.iterdir())) == 1  # the temporary directory
    del w
    gc.collect()
    assert list(tmp_path.iterdir()) == []
