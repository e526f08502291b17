"""Errors name the fix: the loader to use for a file, the ``n_actions`` a feature map was
built for, ``obs[None]`` for a single observation, plain numbers (never ``np.float64(...)``)
for a parameter out of range."""

import re

import numpy as np
import pytest
from helpers import D, linear_data

import r2pvi
from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.features import StateAggregation, cross_actions


def test_loaders_name_the_right_loader(tmp_path):
    data, *_ = linear_data()
    npz, folder = data.save(tmp_path / "data.npz"), data.save(tmp_path / "dir")
    with pytest.raises(ValueError, match="holds a dataset.*OfflineDataset.load"):
        r2pvi.load(npz)
    with pytest.raises(ValueError, match="dataset directory.*OfflineDataset.open"):
        r2pvi.load(folder)
    with pytest.raises(ValueError, match="dataset .npz file.*OfflineDataset.load"):
        OfflineDataset.open(npz)
    with pytest.raises(FileNotFoundError, match="OfflineDataset.load"):
        OfflineDataset.open(tmp_path / "missing.npz")
    model = PEVI().fit(data).save(tmp_path / "m.npz")
    with pytest.raises(ValueError, match="holds an estimator.*r2pvi.load"):
        OfflineDataset.load(model)


def test_n_actions_that_disagree_with_the_feature_map_are_named():
    fmap = cross_actions(StateAggregation(n_bins=2).fit([[0.0], [1.0]]), n_actions=2)
    ep = {"observations": [[0.0], [0.4], [0.9]], "actions": [1, 0], "rewards": [1.0, 1.0],
          "terminations": [False, True], "truncations": [False, False]}
    with pytest.raises(ValueError, match="n_actions=3 disagrees with the feature map, built "
                                         "for n_actions=2"):
        OfflineDataset.from_episodes([ep], fmap, n_actions=3)
    s = np.zeros((2, 1, 1))
    with pytest.raises(ValueError, match="n_actions=3 disagrees"):
        OfflineDataset.from_transitions(s, np.zeros((2, 1), int), np.zeros((2, 1)), s, fmap, 3)
    with pytest.raises(ValueError, match="built for n_actions=2"):
        fmap(np.zeros((1, 1)), np.array([2]))


def test_a_single_observation_is_told_to_be_a_batch():
    obs = np.random.default_rng(0).random((20, 4))
    fmap = cross_actions(StateAggregation(n_bins=2).fit(obs), n_actions=2)
    ep = {"observations": obs[:3], "actions": [1, 0], "rewards": [1.0, 1.0],
          "terminations": [False, True], "truncations": [False, False]}
    policy = PEVI().fit(OfflineDataset.from_episodes([ep], fmap, 2)).as_policy(fmap)
    with pytest.raises(ValueError, match=re.escape("pass obs[None] (shape (1, 4))")):
        policy(0, obs[0])
    assert policy(0, obs[0][None]).shape == (1,)


def test_validation_messages_print_plain_numbers():
    data, *_ = linear_data()
    for est, text in ((DRPVI(-0.1), "got min -0.1"), (DRVIL(np.full(D, -0.5)), "got min -0.5"),
                      (DRPVI(0.1, variance_aware=np.int64(1)), "got 1"),
                      (PEVI(penalty=np.str_("l3")), "got 'l3'")):
        with pytest.raises((TypeError, ValueError)) as info:
            est.fit(data)
        assert text in str(info.value) and "np." not in str(info.value), str(info.value)


def test_an_r_max_of_zero_from_all_zero_rewards_says_why_and_what_to_pass():
    rng = np.random.default_rng(0)
    phi = rng.dirichlet(np.ones(3), (10, 3))
    nphi = rng.dirichlet(np.ones(3), (10, 3, 2))
    zero = OfflineDataset.from_features(phi, np.zeros((10, 3)), nphi)
    assert zero.reward_range == (0.0, 0.0)
    with pytest.raises(ValueError, match=r"every reward in the data is 0.*r_max=1\.0"):
        R2PVI("tv", 1.0, r_max=zero.reward_range[1]).fit(zero)
    some = OfflineDataset.from_features(phi, rng.random((10, 3)), nphi)
    with pytest.raises(ValueError, match=r"^r_max must be > 0, got 0\.0$"):
        R2PVI("tv", 1.0, r_max=0.0).fit(some)
    R2PVI("tv", 1.0, r_max=1.0).fit(zero)  # the bound of the task is accepted
