"""A fit warns (``FeatureSizeWarning``) when the feature map has more features than one
regression has transitions: per step for the per-step form, all of them pooled."""

import warnings

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import PEVI, R2PVI, FeatureSizeWarning, OfflineDataset, StarvedFitWarning


def _dataset(K, H, d, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    return OfflineDataset.from_features(phi, rng.random((K, H)), next_phi)


def _size_warnings(est, ds):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(ds)
    return [str(w.message) for w in caught if issubclass(w.category, FeatureSizeWarning)]


def test_a_per_step_fit_with_more_features_than_rows_per_step_warns_with_the_numbers_and_fix():
    ds = _dataset(K=30, H=5, d=40)
    messages = _size_warnings(PEVI(), ds)
    assert len(messages) == 1
    msg = messages[0]
    assert "d = 40" in msg and "holds 30 transitions" in msg and "5 per-step" in msg
    assert "time_homogeneous=True" in msg and "up to 120 rows" in msg
    assert "StateAggregation" in msg and "fewer" in msg


def test_the_same_features_pooled_over_enough_transitions_do_not_warn():
    ds = _dataset(K=30, H=5, d=40)  # 120 pooled transitions (steps 0..3) >= 40
    assert _size_warnings(R2PVI("tv", lam=0.1, time_homogeneous=True), ds) == []


def test_a_pooled_fit_with_more_features_than_all_transitions_warns():
    ds = _dataset(K=6, H=3, d=25)
    messages = _size_warnings(R2PVI("tv", lam=0.1, time_homogeneous=True), ds)
    assert len(messages) == 1
    assert "d = 25" in messages[0] and "pooled regression holds 12 transitions" in messages[0]
    assert "time_homogeneous" not in messages[0]  # already pooled: not offered as the fix


@settings(max_examples=25, deadline=None)
@given(K=st.integers(2, 25), H=st.integers(1, 4), d=st.integers(2, 30),
       pooled=st.booleans())
@example(K=10, H=3, d=20, pooled=True)  # d == rows: silent
@example(K=10, H=3, d=21, pooled=True)
@example(K=10, H=3, d=10, pooled=False)
@example(K=10, H=3, d=11, pooled=False)
def test_warns_exactly_when_d_exceeds_the_rows_of_the_largest_regression(K, H, d, pooled):
    ds = _dataset(K=K, H=H, d=d)
    messages = _size_warnings(PEVI(time_homogeneous=pooled), ds)
    rows = K * max(H - 1, 1) if pooled else K  # pooled: steps 0 .. H-2 (H = 1: step 0)
    assert len(messages) == (1 if d > rows else 0)


def test_empty_rows_after_an_episode_ends_do_not_count_as_transitions():
    K, H, d = 40, 3, 30
    rng = np.random.default_rng(1)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    phi[8:, 1:] = 0.0  # 32 episodes ended after step 0: 16 transitions at steps 1 and 2
    ds = OfflineDataset.from_features(phi, np.zeros((K, H)),
                                      rng.dirichlet(np.ones(d), size=(K, H, 2)),
                                      check_simplex=False)
    # the largest step (step 0) holds 40 >= 30 rows: no warning though later steps are short
    assert _size_warnings(PEVI(), ds) == []
    ds_short = ds[:20]  # step 0 now holds 20 < 30
    assert len(_size_warnings(PEVI(), ds_short)) == 1


def test_a_dataset_in_files_warns_from_its_shape_without_another_read(tmp_path):
    _dataset(K=10, H=4, d=16).save(tmp_path / "data")
    on_disk = OfflineDataset.open(tmp_path / "data")
    messages = _size_warnings(PEVI(), on_disk)
    assert len(messages) == 1 and "d = 16" in messages[0] and "10 transitions" in messages[0]


def test_the_warning_is_public_and_a_user_warning():
    assert issubclass(r2pvi.FeatureSizeWarning, UserWarning)
    assert "FeatureSizeWarning" in r2pvi.__all__
    assert not issubclass(FeatureSizeWarning, StarvedFitWarning)


def test_an_oversized_tile_coding_on_observations_warns():
    from r2pvi.features import TileCoding, cross_actions

    rng = np.random.default_rng(0)
    K, H = 20, 10
    obs = rng.uniform(-1, 1, size=(K, H + 1, 3))
    fmap = cross_actions(TileCoding(n_tilings=4, n_tiles=4).fit(obs.reshape(-1, 3)), 2)
    ds = OfflineDataset.from_observations(obs[:, :-1], rng.integers(0, 2, (K, H)),
                                          rng.random((K, H)), obs[:, 1:], fmap, n_actions=2)
    with pytest.warns(FeatureSizeWarning, match=f"d = {ds.n_features} "):
        R2PVI("tv", lam=0.1, time_homogeneous=True).fit(ds)
