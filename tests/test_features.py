"""Feature maps: on the simplex, deterministic, vectorized, scikit-learn conventions."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import r2pvi
from r2pvi.features import (
    ActionCrossing,
    NormalizedRBF,
    StateAggregation,
    TileCoding,
    as_feature_map,
    cross_actions,
)

MAPS = [
    lambda: NormalizedRBF(n_centers=3),
    lambda: NormalizedRBF(centers=[[0.0, 0.0], [1.0, 2.0], [5.0, -1.0]], bandwidth=0.3),
    lambda: TileCoding(n_tilings=4, n_tiles=3),
    lambda: TileCoding(n_tilings=3, n_tiles=[2, 5], offsets="random", seed=1),
    lambda: StateAggregation(n_bins=[2, 3]),
]

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(fit=arrays(float, st.tuples(st.integers(1, 20), st.just(2)), elements=finite),
       new=arrays(float, st.tuples(st.integers(1, 10), st.just(2)), elements=finite),
       which=st.integers(0, len(MAPS) - 1), scale=st.sampled_from([1e-8, 1.0, 1e6]))
def test_every_map_lands_on_the_simplex(fit, new, which, scale):
    """Ties, constant dimensions, extreme scales and points outside the fitted range."""
    m = MAPS[which]().fit(fit * scale)
    psi = m.transform(new * scale)
    assert psi.shape == (new.shape[0], m.n_features_out_)
    assert (psi >= 0).all()
    np.testing.assert_allclose(psi.sum(axis=1), 1.0, atol=1e-12)


def test_tile_coding_counts_and_sparse_equals_dense():
    X = np.random.default_rng(0).uniform(-2, 3, size=(200, 3))
    dense = TileCoding(n_tilings=5, n_tiles=4, offsets="random", seed=7).fit(X)
    sparse = TileCoding(n_tilings=5, n_tiles=4, offsets="random", seed=7, sparse=True).fit(X)
    S = sparse.transform(X)
    assert sp.issparse(S) and S.format == "csr" and S.nnz == 200 * 5
    np.testing.assert_array_equal(S.toarray(), dense.transform(X))
    # Each tiling contributes one active tile in its own block.
    cols = dense.active_tiles(X)
    assert (cols // dense.tiling_size_ == np.arange(5)).all()
    # Deterministic for a seed, different for another.
    again = TileCoding(n_tilings=5, n_tiles=4, offsets="random", seed=7).fit(X)
    np.testing.assert_array_equal(again.tile_offsets_, dense.tile_offsets_)
    other = TileCoding(n_tilings=5, n_tiles=4, offsets="random", seed=8).fit(X)
    assert not np.array_equal(other.tile_offsets_, dense.tile_offsets_)


def test_tile_coding_generalizes_between_neighbours():
    tc = TileCoding(n_tilings=8, n_tiles=4).fit([[0.0], [1.0]])
    psi = tc.transform([[0.50], [0.52], [0.95]])
    overlap_near = (psi[0] * psi[1]).sum() * 8
    overlap_far = (psi[0] * psi[2]).sum() * 8
    assert overlap_near > overlap_far


def test_rbf_grid_and_closed_form():
    rbf = NormalizedRBF(n_centers=[3, 2]).fit([[0.0, 10.0], [2.0, 20.0]])
    assert rbf.centers_.shape == (6, 2) and rbf.n_features_out_ == 6
    x = np.array([[0.5, 12.0]])
    z = (x - [0.0, 10.0]) / [2.0, 10.0]
    sigma = np.array([0.5, 1.0])
    logits = -0.5 * (((z - rbf.centers_) / sigma) ** 2).sum(axis=1)
    expected = np.exp(logits) / np.exp(logits).sum()
    np.testing.assert_allclose(rbf.transform(x)[0], expected, rtol=1e-12)


def test_action_crossing_blocks_dense_and_sparse():
    X = np.random.default_rng(1).normal(size=(30, 2))
    a = np.arange(30) % 3
    for sparse in (False, True):
        fmap = cross_actions(TileCoding(n_tilings=2, n_tiles=2, sparse=sparse).fit(X), 3)
        phi = fmap(X, a)
        phi = phi.toarray() if sparse else phi
        m = fmap.state_map.n_features_out_
        assert phi.shape == (30, 3 * m) == (30, fmap.n_features_out_)
        psi = fmap.state_features(X)
        psi = psi.toarray() if sparse else psi
        for i in range(30):
            blocks = phi[i].reshape(3, m)
            np.testing.assert_array_equal(blocks[a[i]], psi[i])
            assert blocks.sum() == pytest.approx(1.0)
        all_a = fmap.all_actions(X)
        np.testing.assert_array_equal(all_a[np.arange(30), a], phi)


class OneHotBins:
    """A fitted transformer from elsewhere (scikit-learn's interface, no r2pvi base)."""

    def transform(self, X):
        idx = np.clip((np.asarray(X)[:, 0] > 0).astype(int), 0, 1)
        return np.eye(2)[idx]


def test_sklearn_conventions_and_foreign_transformers():
    m = TileCoding(n_tilings=3, n_tiles=2, seed=4)
    assert m.get_params()["n_tilings"] == 3
    c = type(m)(**m.get_params())  # what sklearn.base.clone does
    assert c.get_params() == m.get_params() and not hasattr(c, "low_")
    X = np.random.default_rng(2).normal(size=(40, 2))
    assert m.fit(X) is m
    with pytest.raises(r2pvi.NotFittedError, match="not fitted"):
        NormalizedRBF().transform(X)
    with pytest.raises(ValueError, match="dimensions"):
        m.transform(np.zeros((3, 5)))
    with pytest.raises(ValueError, match="invalid parameter"):
        m.set_params(bins=3)
    assert m.set_params(n_tiles=3) is m and m.fit(X).n_features_out_ == 3 * 16
    fmap = as_feature_map(OneHotBins(), 2)
    assert isinstance(fmap, ActionCrossing)
    np.testing.assert_array_equal(fmap(np.array([[-1.0], [2.0]]), np.array([1, 0])),
                                  [[0, 0, 1, 0], [0, 1, 0, 0]])


def test_feature_map_errors():
    with pytest.raises(TypeError, match="numeric"):
        NormalizedRBF().fit(np.array([["a"]]))
    with pytest.raises(ValueError, match="NaN"):
        StateAggregation().fit([[np.nan]])
    with pytest.raises(ValueError, match="ranges"):
        StateAggregation(ranges=[[0, np.inf]]).fit([[0.0]])
    with pytest.raises(ValueError, match="n_bins"):
        StateAggregation(n_bins=0).fit([[0.0]])
    with pytest.raises(ValueError, match="offsets"):
        TileCoding(offsets="grid").fit([[0.0]])
    with pytest.raises(TypeError, match="transform"):
        cross_actions(object(), 2)
    with pytest.raises(ValueError, match="actions must lie"):
        cross_actions(StateAggregation().fit([[0.0]]), 2)(np.zeros((1, 1)), np.array([2]))
    X = np.zeros((4, 1))
    before = X.copy()
    StateAggregation(ranges=[[-1, 1]]).fit(X).transform(X)
    np.testing.assert_array_equal(X, before)


def test_fitted_maps_save_and_load(tmp_path):
    from r2pvi.features import load_feature_map

    X = np.random.default_rng(3).normal(size=(60, 2)) * [1.0, 50.0]
    maps = [NormalizedRBF(n_centers=[3, 2], bandwidth=0.4),
            NormalizedRBF(centers=X[:5], ranges=[[-3, 3], [-100, 100]]),
            TileCoding(n_tilings=3, n_tiles=[2, 4], offsets="random", seed=9, sparse=True),
            StateAggregation(n_bins=4)]
    for i, m in enumerate(maps):
        m.fit(X)
        back = load_feature_map(m.save(tmp_path / f"m{i}"))
        assert type(back) is type(m)
        a, b = back.transform(X), m.transform(X)
        a, b = (a.toarray(), b.toarray()) if sp.issparse(a) else (a, b)
        np.testing.assert_array_equal(a, b)
    fmap = cross_actions(maps[0], 3)
    back = load_feature_map(fmap.save(tmp_path / "crossed.npz"))
    acts = np.arange(60) % 3
    np.testing.assert_array_equal(back(X, acts), fmap(X, acts))
    with pytest.raises(r2pvi.NotFittedError, match="not fitted"):
        StateAggregation().save(tmp_path / "x.npz")
    with pytest.raises(TypeError, match="Generator"):
        TileCoding(offsets="random", seed=np.random.default_rng(0)).fit(X).save(tmp_path / "g")
    with pytest.raises(TypeError, match="r2pvi's feature maps"):
        from r2pvi.features import save_feature_map

        save_feature_map(cross_actions(OneHotBins(), 2), tmp_path / "o.npz")
