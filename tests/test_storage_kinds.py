"""A fit is the same wherever the data lives and however a step is cut into chunks.

The storage kinds: arrays in memory (float64 or float32, step-major views without a copy), a
dataset directory (saved or written by chunks), Dask arrays on a local cluster, a next-state
feature table (finite MDPs), observations and a feature map (features computed chunk by
chunk), known next-state values in place of features. The truth for every fit is the
in-memory fit of the same numbers; a fit streamed from disk never holds a step's features.
The directory format itself is tested in test_dataset_directory.py, the writer in
test_dataset_writer.py, the behaviour next-state form in test_next_form_behaviour.py.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from storage_helpers import (
    ESTIMATORS,
    A,
    D,
    H,
    K,
    assert_same_fit,
    dask_and_memory,
    make_arrays,
    set_chunk,
)

import r2pvi
from r2pvi import DatasetWriter, OfflineDataset, engine
from r2pvi.data.storage import CHUNK
from r2pvi.envs import FiniteLinearMDP


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_fit_is_the_same_in_memory_on_disk_and_in_any_chunking(stored, name):
    mem, saved, written = stored
    ref = ESTIMATORS[name]().fit(mem)
    for ds in (OfflineDataset.open(saved), OfflineDataset.open(written)):
        assert ds.storage == "disk"
        set_chunk(ds, 97)  # force many chunks per step
        assert_same_fit(ESTIMATORS[name]().fit(ds), ref)
    set_chunk(mem, 1)
    try:
        assert_same_fit(ESTIMATORS[name]().fit(mem), ref)
    finally:
        set_chunk(mem, CHUNK)


@settings(max_examples=15, deadline=None)
@given(chunk=st.integers(1, 80), k=st.integers(1, 60), seed=st.integers(0, 2**16))
def test_next_state_values_do_not_depend_on_the_chunking(chunk, k, seed):
    phi, rewards, nphi, nv = make_arrays(k, seed)
    ds = OfflineDataset.from_features(phi, rewards, nphi, nv, check_simplex=False)
    ref = r2pvi.R2PVI("kl", 0.5, beta=0.05).fit(ds)
    set_chunk(ds, chunk)
    assert_same_fit(r2pvi.R2PVI("kl", 0.5, beta=0.05).fit(ds), ref)


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
    set_chunk(ds, 64)
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
    set_chunk(saved, 100)
    assert_same_fit(ESTIMATORS["TV"]().fit(saved), ESTIMATORS["TV"]().fit(dense))
    assert_same_fit(ESTIMATORS["TV"]().fit(saved.subset([5, 2, 9])),
                    ESTIMATORS["TV"]().fit(dense.subset([5, 2, 9])))
    with pytest.raises(ValueError, match=r"actions must lie in \[0, 3\)"):
        OfflineDataset.from_observations(obs, act + 1, rewards, nxt, fmap, A)


def test_dask_arrays_on_a_local_cluster_fit_as_in_memory(cluster_client):
    ds, mem = dask_and_memory(250)
    phi, rewards, nphi, _ = make_arrays()
    assert ds.storage == "dask" and ds.n_trajectories == K
    for name in ("TV", "chi2"):
        assert_same_fit(ESTIMATORS[name]().fit(ds), ESTIMATORS[name]().fit(mem))
    with pytest.raises(TypeError, match="dask.array"):
        OfflineDataset.from_dask(phi, rewards, nphi)


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


# ---------------------------------------------------------------- streamed fits
@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Other numbers (seed 3) in memory and saved as a directory."""
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
    set_chunk(ds, 61)
    assert_same_fit(ESTIMATORS[name]().fit(ds), ref)
    # again, now from the Gram matrices the first fit (or the file) left in the cache
    assert_same_fit(ESTIMATORS[name]().fit(ds), ref)


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
        set_chunk(ds, 64)
        ESTIMATORS[name]().fit(ds)  # imports, caches, the reader thread
        tracemalloc.start()
        try:
            ESTIMATORS[name]().fit(ds)
            peaks[name] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peaks["TV"] < 0.4 * step_bytes, peaks
    assert peaks["chi2"] > step_bytes, peaks
