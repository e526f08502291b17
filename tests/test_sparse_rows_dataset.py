"""Sparse rows are a storage kind of the one OfflineDataset: a dataset built from sparse rows
honours the whole contract of the class (constructors, properties, subsets) and gives the
dense dataset's numbers."""

import importlib
import pkgutil

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.sparse import SparseOfflineDataset

K, H, A, D = 9, 3, 2, 7


def _arrays(seed=0, known=True):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), size=(K, H))
    phi[phi < 0.1] = 0.0  # some zeros: sparse rows store fewer entries
    next_phi = rng.dirichlet(np.ones(D), size=(K, H, A))
    rewards = rng.random((K, H))
    nv = None
    if known:
        nv = np.full((K, H, A), np.nan)
        nv[::3, :, 1] = 0.0  # absorbing next states of known value 0
    return phi, rewards, next_phi, nv


def _both(seed=0, known=True):
    """The same data as dense arrays and as sparse rows."""
    phi, rewards, next_phi, nv = _arrays(seed, known)
    dense = OfflineDataset.from_features(phi, rewards, next_phi, nv, check_simplex=False)
    sparse = SparseOfflineDataset.from_rows(  # the docs' name, on every version
        [sp.csr_matrix(phi[:, h]) for h in range(H)], rewards,
        [sp.csr_matrix(next_phi[:, h].reshape(K * A, D)) for h in range(H)], A, nv)
    return dense, sparse


def _same_steps(a, b):
    for h in range(a.horizon):
        x, y = a.step(h), b.step(h)
        np.testing.assert_array_equal(x[0], y[0].toarray())
        np.testing.assert_array_equal(x[1], y[1])
        np.testing.assert_array_equal(x[2], y[2].matrix.toarray().reshape(x[2].shape))
        if h < a.horizon - 1:
            assert (x[3] is None) == (y[3] is None)
            if x[3] is not None:
                np.testing.assert_array_equal(x[3], y[3])


def test_no_class_in_the_library_subclasses_offline_dataset():
    for info in pkgutil.walk_packages(r2pvi.__path__, "r2pvi."):
        if not info.name.endswith("__main__"):
            importlib.import_module(info.name)
    assert OfflineDataset.__subclasses__() == []


def test_a_dataset_of_sparse_rows_is_an_offline_dataset_of_sparse_storage():
    dense, sparse = _both()
    direct = OfflineDataset.from_sparse_rows(
        [sparse.step(h)[0] for h in range(H)], sparse.rewards,
        [sparse.step(h)[2].matrix for h in range(H)], A, sparse.next_values)
    for ds in (sparse, direct):
        assert type(ds) is OfflineDataset
        assert ds.storage == "memory (sparse rows)" and ds.dtype == np.float64
        assert (ds.n_trajectories, ds.horizon, ds.n_features, ds.n_actions) == (K, H, D, A)
        assert "sparse rows, nnz(phi)=" in repr(ds)
    assert dense.storage == "memory" and "sparse" not in repr(dense)
    with pytest.raises(TypeError, match="not a class of datasets"):
        SparseOfflineDataset()


def test_its_class_builds_datasets_of_every_kind():
    """The class of a dataset of sparse rows is the one class: its constructors work (a
    subclass that skipped the base __init__ made from_features a TypeError)."""
    _, sparse = _both()
    phi, rewards, next_phi, nv = _arrays(1)
    ds = type(sparse).from_features(phi, rewards, next_phi, nv, check_simplex=False)
    assert type(ds) is OfflineDataset and ds.storage == "memory"


@pytest.mark.parametrize("known", [True, False])
def test_known_values_and_observations_as_the_dense_dataset_says(known):
    dense, sparse = _both(known=known)
    assert sparse.has_known_values is dense.has_known_values is known
    np.testing.assert_array_equal(sparse.next_values, dense.next_values)
    assert sparse.states is None and sparse.actions is None and sparse.next_states is None
    assert sparse.reward_range == dense.reward_range and sparse.reward_noise == 0.0
    assert sparse.nonnegative_features and sparse.nonnegative_next_features


def test_subset_refuses_a_mask_of_the_wrong_length():
    _, sparse = _both()
    for n in (K - 1, K + 1):
        with pytest.raises(ValueError, match=f"one entry per trajectory \\(K = {K}\\)"):
            sparse.subset(np.ones(n, dtype=bool))


def test_subset_refuses_indices_out_of_range():
    _, sparse = _both()
    for bad in ([K + 1], [-1], [0, K]):
        with pytest.raises(ValueError, match=f"indices must lie in \\[0, {K}\\)"):
            sparse.subset(bad)
    with pytest.raises(ValueError, match="at least one trajectory"):
        sparse.subset(np.zeros(K, dtype=bool))


@settings(max_examples=40, deadline=None)
@given(st.one_of(st.lists(st.integers(0, K - 1), min_size=1, max_size=2 * K),
                 st.lists(st.booleans(), min_size=K, max_size=K).filter(any)))
def test_subsets_of_sparse_rows_hold_the_dense_subsets_numbers(selection):
    dense, sparse = _both()
    idx = np.array(selection)
    a, b = dense.subset(idx), sparse.subset(idx)
    assert b.storage == "memory (sparse rows)" and b.n_trajectories == a.n_trajectories
    _same_steps(a, b)
    np.testing.assert_array_equal(b.rewards, a.rewards)
    np.testing.assert_array_equal(b.next_values, a.next_values)


def test_steps_and_products_are_the_dense_datasets():
    dense, sparse = _both()
    _same_steps(dense, sparse)
    z = np.linspace(-1.0, 1.0, D)
    for h in range(H):
        np.testing.assert_allclose(sparse.step_times(h, z), dense.step_times(h, z), rtol=1e-14)
        assert sp.issparse(sparse.step_phi(h))


@pytest.mark.parametrize("time_homogeneous", [False, True])
def test_fits_on_sparse_rows_give_the_dense_fit(time_homogeneous):
    dense, sparse = _both()
    for make in (lambda: R2PVI("tv", 0.3, beta=0.1, time_homogeneous=time_homogeneous),
                 lambda: PEVI(beta=0.1, time_homogeneous=time_homogeneous)):
        np.testing.assert_allclose(make().fit(sparse).weights_, make().fit(dense).weights_,
                                   rtol=0, atol=1e-10)


def test_dense_views_and_saving_are_refused_without_densifying(tmp_path):
    _, sparse = _both()
    with pytest.raises(TypeError, match="no dense phi"):
        sparse.phi  # noqa: B018
    with pytest.raises(TypeError, match="no dense next_phi"):
        sparse.next_phi  # noqa: B018
    with pytest.raises(TypeError, match="cannot save a dataset of sparse rows"):
        sparse.save(tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
