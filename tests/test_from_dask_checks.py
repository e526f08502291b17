"""OfflineDataset.from_dask checks what it can without computing (types, dtypes, shapes,
chunk sizes), as from_features checks them, and computes nothing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from r2pvi import OfflineDataset

da = pytest.importorskip("dask.array")

K, H, A, D = 12, 3, 2, 4


def _arrays(rng=None):
    rng = np.random.default_rng(0) if rng is None else rng
    return (rng.dirichlet(np.ones(D), (K, H)), rng.random((K, H)),
            rng.dirichlet(np.ones(D), (K, H, A)), np.full((K, H, A), np.nan))


def _lazy(*arrays):
    return [da.from_array(a, chunks=(5,) + a.shape[1:]) for a in arrays]


def _never_computed(a):
    """A Dask array whose computation fails: building a dataset of it must not compute."""
    def fail(block):
        raise AssertionError("from_dask computed an array")
    return da.from_array(a, chunks=(5,) + a.shape[1:]).map_blocks(fail, dtype=a.dtype)


def test_nothing_is_computed():
    ds = OfflineDataset.from_dask(*(_never_computed(a) for a in _arrays()))
    assert ds.storage == "dask" and (ds.n_trajectories, ds.horizon, ds.n_actions) == (K, H, A)


@pytest.mark.parametrize("which", [0, 1, 2, 3])
def test_complex_and_non_numeric_arrays_are_refused_by_name(which):
    name = ("phi", "rewards", "next_phi", "next_values")[which]
    for bad, text in ((lambda a: a.astype(complex), "must be real"),
                      (lambda a: a.astype(str), "must be a numeric")):
        arrays = list(_arrays())
        arrays[which] = bad(arrays[which])
        with pytest.raises(TypeError, match=f"{name} {text}"):
            OfflineDataset.from_dask(*_lazy(*arrays))


def test_unknown_chunk_sizes_are_refused_without_computing():
    phi, rewards, nphi, nv = _lazy(*_arrays())
    unknown = phi[phi[:, 0, 0] > -1.0]  # a boolean selection: chunk sizes unknown (NaN)
    assert np.isnan(unknown.shape[0])
    with pytest.raises(ValueError, match="phi has unknown chunk sizes.*compute_chunk_sizes"):
        OfflineDataset.from_dask(unknown, rewards, nphi, nv)


def test_empty_dimensions_are_refused_as_from_features_refuses_them():
    phi, rewards, nphi, nv = _arrays()
    with pytest.raises(ValueError, match="K = 0 trajectories"):
        OfflineDataset.from_dask(*_lazy(phi[:0], rewards[:0], nphi[:0], nv[:0]))
    with pytest.raises(ValueError, match="A = 0 actions"):
        OfflineDataset.from_dask(*_lazy(phi, rewards, nphi[:, :, :0], nv[:, :, :0]))


@settings(max_examples=30, deadline=None)
@given(which=st.sampled_from([1, 2, 3]), axis=st.integers(0, 3), delta=st.sampled_from([-1, 1]))
def test_a_shape_that_disagrees_with_phi_names_the_argument(which, axis, delta):
    arrays = list(_arrays())
    a = arrays[which]
    axis = axis % a.ndim
    shape = list(a.shape)
    shape[axis] += delta
    if which == 2 and axis == 2:  # A is next_phi's own: make next_values disagree instead
        which, a = 3, arrays[3]
        shape = list(a.shape)
        shape[2] += delta
    arrays[which] = np.zeros(shape)
    name = ("phi", "rewards", "next_phi", "next_values")[which]
    with pytest.raises(ValueError, match=f"^{name} must have shape"):
        OfflineDataset.from_dask(*_lazy(*arrays))


def test_integer_features_are_stored_as_float64_and_fit_as_in_memory():
    from r2pvi import R2PVI

    rng = np.random.default_rng(3)
    phi = rng.integers(0, 2, (K, H, D))
    nphi = rng.integers(0, 2, (K, H, A, D))
    rewards = rng.random((K, H))
    ds = OfflineDataset.from_dask(*_lazy(phi, rewards, nphi))
    mem = OfflineDataset.from_features(phi, rewards, nphi, check_simplex=False)
    assert ds.dtype == mem.dtype == np.float64
    np.testing.assert_allclose(R2PVI("tv", 0.3, beta=0.1).fit(ds).weights_,
                               R2PVI("tv", 0.3, beta=0.1).fit(mem).weights_, rtol=1e-12)
