"""A new user's findings (session 6): rewards outside [0, r_max], saves that destroyed files,
errors that did not name the fix, a doc snippet that did not run, string options."""

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from extras import require

import r2pvi
from r2pvi import DRPVI, DRVIL, PEVI, R2PVI, DatasetWriter, OfflineDataset
from r2pvi.envs import HardInstance
from r2pvi.features import StateAggregation, cross_actions
from r2pvi.sparse import SparseOfflineDataset

ROOT = Path(__file__).resolve().parents[1]
K, H, D, A = 60, 3, 4, 2


def _data(scale=1.0, shift=0.0, seed=0, **kw):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), size=(K, H))
    nxt = rng.dirichlet(np.ones(D), size=(K, H, A))
    theta = rng.uniform(size=(H, D))
    r = scale * np.einsum("khd,hd->kh", phi, theta) + shift
    return OfflineDataset.from_features(phi, r, nxt, **kw), phi, r, nxt, theta


ESTIMATORS = [lambda **kw: PEVI(beta=0.0, **kw), lambda **kw: R2PVI("tv", lam=1.0, **kw),
              lambda **kw: R2PVI("kl", lam=1.0, **kw), lambda **kw: DRPVI(0.1, **kw),
              lambda **kw: DRVIL(0.1, **kw)]


# ---------------------------------------------------------------- 1. rewards and r_max
@pytest.mark.parametrize("make", ESTIMATORS)
def test_fit_refuses_rewards_above_r_max_and_names_the_fix(make):
    data, *_ = _data(scale=5.0)
    high = data.reward_range[1]
    assert high == float(np.max(data.rewards)) > 1.0
    with pytest.raises(ValueError, match=re.escape(f"reach {high!r} > r_max=1.0; pass "
                                                   f"r_max={high!r} or larger")):
        make().fit(data)
    est = make(r_max=high).fit(data)  # the suggested r_max fits, and Q is not the clip
    q = est.q_values(data.next_phi[:, 0], 0)
    assert np.ptp(q) > 0 and q.max() < H * high


@pytest.mark.parametrize("make", ESTIMATORS[:2])
def test_fit_refuses_negative_rewards_and_says_how_to_shift_them(make):
    data, phi, r, nxt, _ = _data(shift=-2.0)
    low, high = data.reward_range
    with pytest.raises(ValueError, match="reward_offset='auto'") as info:
        make().fit(data)
    message = str(info.value)
    assert f"go down to {low!r} < 0" in message and f"c >= {-low!r}" in message
    assert f"{high - low!r} for c = {-low!r}" in message
    shifted = OfflineDataset.from_features(phi, r - low, nxt)  # the shift the message asks
    make(r_max=shifted.reward_range[1]).fit(shifted)


def test_reward_check_allows_rounding_only():
    _, phi, r, nxt, _ = _data()
    r = r / r.max()
    PEVI().fit(OfflineDataset.from_features(phi, r * (1 + 1e-13), nxt))
    PEVI().fit(OfflineDataset.from_features(phi, r - r.min() - 1e-13, nxt))
    with pytest.raises(ValueError, match="r_max"):
        PEVI().fit(OfflineDataset.from_features(phi, r * (1 + 1e-9), nxt))
    with pytest.raises(ValueError, match="< 0"):
        PEVI().fit(OfflineDataset.from_features(phi, r - r.min() - 1e-9, nxt))


def test_reward_weights_are_checked_through_the_rewards_they_give(monkeypatch):
    data, phi, r, nxt, theta = _data()
    with pytest.raises(ValueError, match="phi_h\\^T theta_h of reward_weights reach"):
        PEVI(reward_weights=3 * theta).fit(data)
    with pytest.raises(ValueError, match="go down to .* < 0 on the data"):
        PEVI(reward_weights=theta - 2).fit(data)
    # On simplex rows, theta_h in [0, r_max] settles it without reading a feature.
    monkeypatch.setattr(OfflineDataset, "_step_product",
                        lambda *a: pytest.fail("read the features"))
    PEVI(reward_weights=theta).fit(data)
    monkeypatch.undo()
    # Off the simplex the bound says nothing: the rewards phi theta are computed, exactly.
    off = OfflineDataset.from_features(phi * 1.5, r, nxt, check_simplex=False)
    with pytest.raises(ValueError, match="reach"):
        PEVI(reward_weights=theta).fit(off)
    small = theta / (1.5 * theta.max())  # phi theta <= 1 although rows sum to 1.5
    PEVI(reward_weights=small).fit(off)


def test_reward_range_comes_from_validation_the_manifest_or_one_read(tmp_path, monkeypatch):
    data, phi, r, nxt, _ = _data(scale=5.0)
    expect = (float(r.min()), float(r.max()))
    assert data._source.reward_range == expect  # taken while validating
    path = data.save(tmp_path / "dir")
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["reward_range"] == list(expect)
    opened = OfflineDataset.open(path)
    monkeypatch.setattr(type(opened._source.rewards), "read",
                        lambda *a, **k: pytest.fail("read the rewards"))
    assert opened.reward_range == expect
    with pytest.raises(ValueError, match="r_max"):
        PEVI().fit(opened)
    monkeypatch.undo()
    with DatasetWriter(tmp_path / "w", horizon=H, n_features=D, n_actions=A) as w:
        w.append(phi[:30], r[:30], nxt[:30])
        w.append(phi[30:], r[30:], nxt[30:])
    assert json.loads((tmp_path / "w" / "manifest.json").read_text())["reward_range"] == \
        list(expect)
    del manifest["reward_range"]  # a directory written before: the rewards are read once
    (path / "manifest.json").write_text(json.dumps(manifest))
    assert OfflineDataset.open(path).reward_range == expect
    assert data.subset(np.arange(5)).reward_range == (float(r[:5].min()), float(r[:5].max()))


def test_reward_check_on_sparse_and_dask_datasets():
    import scipy.sparse as sp

    _, phi, r, nxt, _ = _data(scale=5.0)
    sparse = SparseOfflineDataset.from_rows(
        [sp.csr_matrix(phi[:, h]) for h in range(H)], r,
        [sp.csr_matrix(nxt[:, h].reshape(K * A, D)) for h in range(H)], A)
    assert sparse.reward_range == (float(r.min()), float(r.max()))
    with pytest.raises(ValueError, match="r_max"):
        R2PVI("tv").fit(sparse)
    da = require("dask.array")
    lazy = OfflineDataset.from_dask(da.from_array(phi, chunks=(20, H, D)),
                                    da.from_array(r, chunks=(20, H)),
                                    da.from_array(nxt, chunks=(20, H, A, D)))
    assert lazy.reward_range == (float(r.min()), float(r.max()))


def test_noisy_rewards_pass_within_their_noise_and_a_wrong_scale_does_not():
    with pytest.warns(UserWarning, match="lemma"):
        env = HardInstance.lower_bound_instance(2, 3, 1.0, 30, "tv", seed=0)
    data = env.collect(100, policy="behavior", seed=1)
    assert data.reward_noise == 1.0 and data.reward_range[0] < 0  # N(r, 1) samples
    R2PVI("tv").fit(data)
    _, phi, r, nxt, _ = _data()
    noisy = r + 0.1 * np.random.default_rng(1).standard_normal(r.shape)
    with pytest.raises(ValueError, match="< 0"):
        PEVI().fit(OfflineDataset.from_features(phi, noisy, nxt))
    PEVI().fit(OfflineDataset.from_features(phi, noisy, nxt, reward_noise=0.1))
    with pytest.raises(ValueError, match="8 standard deviations of the dataset's reward_noise"):
        PEVI().fit(OfflineDataset.from_features(phi, 5 * r, nxt, reward_noise=0.1))


def test_reward_noise_survives_subset_and_saves(tmp_path):
    data, *_ = _data(reward_noise=0.25)
    assert data.subset([0, 1]).reward_noise == 0.25
    assert OfflineDataset.open(data.save(tmp_path / "d")).reward_noise == 0.25
    assert OfflineDataset.load(data.save(tmp_path / "d.npz")).reward_noise == 0.25
    with pytest.raises(ValueError, match="reward_noise must be >= 0"):
        _data(reward_noise=-1.0)


def test_pendulum_rewards_shifted_by_auto_need_their_r_max():
    require("gymnasium")
    import gymnasium as gym

    from r2pvi.envs import collect_episodes
    from r2pvi.envs.perturbations import DiscreteTorque
    from r2pvi.episodes import episode_observations

    env = DiscreteTorque(gym.make("Pendulum-v1"), n_levels=3)
    eps = collect_episodes(env, "uniform", n_episodes=4, seed=0, max_steps=10)
    fmap = cross_actions(StateAggregation(n_bins=3).fit(episode_observations(eps)), 3)
    data = OfflineDataset.from_episodes(eps, fmap, n_actions=3, reward_offset="auto")
    high = data.reward_range[1]
    assert high > 1.0
    with pytest.raises(ValueError, match=re.escape(f"pass r_max={high!r} or larger")):
        R2PVI("tv", lam=1.0).fit(data)
    R2PVI("tv", lam=1.0, r_max=high).fit(data)


# ---------------------------------------------------------------- 2. saves never destroy
def test_dataset_npz_save_refuses_an_existing_file_unless_overwrite(tmp_path):
    data, *_ = _data()
    other, *_ = _data(seed=1)
    path = data.save(tmp_path / "x.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        other.save(path)
    assert path.read_bytes() == before
    other.save(path, overwrite=True)
    assert np.array_equal(OfflineDataset.load(path).phi, other.phi)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npz"]  # no temporary left


def test_estimator_save_never_writes_over_a_dataset_or_a_directory(tmp_path):
    data, *_ = _data()
    est = PEVI().fit(data)
    folder = data.save(tmp_path / "mem_dir")
    with pytest.raises(IsADirectoryError, match="dataset directory.*mem_dir.npz"):
        est.save(folder)
    assert not (tmp_path / "mem_dir.npz").exists()
    kept = data.save(tmp_path / "data.npz")
    before = kept.read_bytes()
    with pytest.raises(FileExistsError, match="holds a dataset"):
        est.save(kept)
    assert kept.read_bytes() == before
    foreign = tmp_path / "mine.npz"
    np.savez(foreign, a=np.ones(3))
    with pytest.raises(FileExistsError, match="r2pvi did not write"):
        est.save(foreign)
    (tmp_path / "empty.npz").touch()  # an empty file (tempfile's) holds nothing to lose
    assert r2pvi.load(est.save(tmp_path / "empty.npz")).n_actions_ == A
    model = est.save(tmp_path / "model.npz")
    PEVI(beta=0.5).fit(data).save(model)  # a model replaces a model
    assert r2pvi.load(model).beta == 0.5


def test_directory_save_over_a_dataset_file_leaves_nothing_behind(tmp_path):
    data, *_ = _data()
    path = tmp_path / "d"
    data.save(path.with_suffix(".npz")).rename(path)  # a dataset file without a suffix
    with pytest.raises(FileExistsError):
        data.save(path)
    data.save(path, overwrite=True)
    assert path.is_dir() and sorted(p.name for p in tmp_path.iterdir()) == ["d"]


# ---------------------------------------------------------------- 3. errors name the fix
def test_loaders_name_the_right_loader(tmp_path):
    data, *_ = _data()
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
    data, *_ = _data()
    for est, text in ((DRPVI(-0.1), "got min -0.1"), (DRVIL(np.full(D, -0.5)), "got min -0.5"),
                      (DRPVI(0.1, variance_aware=np.int64(1)), "got 1"),
                      (PEVI(penalty=np.str_("l3")), "got 'l3'")):
        with pytest.raises((TypeError, ValueError)) as info:
            est.fit(data)
        assert text in str(info.value) and "np." not in str(info.value), str(info.value)


# ---------------------------------------------------------------- 4. docs
def test_large_feature_spaces_snippet_runs_as_written(capsys):
    require("gymnasium")
    text = (ROOT / "docs" / "large-feature-spaces.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks
    for code in blocks:
        exec(compile(code, "large-feature-spaces.md", "exec"), {})  # noqa: S102
    assert "memory (sparse rows) 10000 (20, 10000)" in capsys.readouterr().out


def test_docs_no_longer_say_datasets_are_dense_and_readme_shows_load():
    guide = (ROOT / "docs" / "your-own-task.md").read_text()
    assert "dense\nfor now" not in guide and "sparse engine path is planned" not in guide
    assert "SparseOfflineDataset" in guide
    assert "OfflineDataset.load(path)" in (ROOT / "README.md").read_text()


# ---------------------------------------------------------------- 5. small
def test_one_episode_warns_that_it_has_no_standard_error():
    require("gymnasium")
    import gymnasium as gym

    from r2pvi.evaluation import evaluate_policy

    with pytest.warns(UserWarning, match="n_episodes >= 2"):
        mean, se = evaluate_policy(gym.make("CartPole-v1"), "uniform", 1, seed=0, max_steps=5)
    assert np.isnan(se) and mean > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isfinite(evaluate_policy(gym.make("CartPole-v1"), "uniform", 2, seed=0,
                                           max_steps=5)[1])


def test_string_options_are_case_insensitive():
    data, *_ = _data()
    for make, upper, lower in ((lambda p: R2PVI("tv", penalty=p), "L1", "l1"),
                               (lambda p: PEVI(penalty=p), "Elliptical", "elliptical"),
                               (lambda v: R2PVI("tv", v_min=v), "DATA", "data"),
                               (lambda v: R2PVI(v), "KL", "kl")):
        a, b = make(upper).fit(data), make(lower).fit(data)
        assert np.array_equal(a.weights_, b.weights_)
        phi_all = data.next_phi[:4, 0]
        assert np.array_equal(a.q_values(phi_all, 0), b.q_values(phi_all, 0))
    policy = PEVI().fit(data).as_policy(lambda o, a: np.eye(D)[a % D], beyond_horizon="Last")
    assert policy.beyond_horizon == "last"
