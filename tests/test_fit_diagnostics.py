"""A fit records what it saw of its regressions (``fit_report_``) and says when a per-step
fit starves (``StarvedFitWarning``)."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import DRPVI, PEVI, R2PVI, OfflineDataset, StarvedFitWarning
from r2pvi.envs import SimulatedLinearMDP


def _dataset(K, H, d, A=2, seed=0, next_values=None):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    rewards = rng.random((K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    return OfflineDataset.from_features(phi, rewards, next_phi, next_values)


def _constant_fit(x, gamma=1.0):
    """The mean fitted value of the constant target 1: an independent ridge fit."""
    theta = np.linalg.solve(x.T @ x + gamma * np.eye(x.shape[1]), x.T @ np.ones(len(x)))
    return float(np.mean(x @ theta))


def test_a_starved_per_step_fit_warns_with_the_fix_and_records_a_short_horizon():
    ds = _dataset(K=30, H=40, d=60)
    with pytest.warns(StarvedFitWarning, match="time_homogeneous=True") as rec:
        est = R2PVI("tv", lam=0.5).fit(ds)
    assert "implicit horizon" in str(rec[0].message)
    report = est.fit_report_
    assert not report.pooled and report.rows.tolist() == [30] * 40
    assert report.implicit_horizon < 40 / 4
    assert "STARVED" in report.summary()


def test_the_same_data_pooled_does_not_warn():
    ds = _dataset(K=30, H=40, d=60)
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFitWarning)
        est = R2PVI("tv", lam=0.5, time_homogeneous=True).fit(ds)
    report = est.fit_report_
    assert report.pooled and report.rows.tolist() == [30 * 39]
    assert report.starved() == []


@pytest.mark.parametrize("K", [12, 80])  # K < d: dual form; K > d: the chunked primal form
@pytest.mark.parametrize("pooled", [False, True])
def test_recorded_shrinkage_equals_an_independent_ridge_fit_of_a_constant(K, pooled):
    H, d = 5, 20
    ds = _dataset(K=K, H=H, d=d, seed=K)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StarvedFitWarning)
        report = PEVI(gamma=0.7, time_homogeneous=pooled).fit(ds).fit_report_
    phi = ds.phi  # (K, H, d)
    if pooled:
        x = np.concatenate([phi[:, h] for h in range(H - 1)])
        expected = [_constant_fit(x, 0.7)]
        mass = np.sum(x * x, axis=0)
    else:
        expected = [_constant_fit(phi[:, h], 0.7) for h in range(H)]
        mass = np.sum(phi[:, -1] ** 2, axis=0)
    np.testing.assert_allclose(report.constant_fit, expected, rtol=1e-10)
    assert report.feature_mass[-1] == pytest.approx(np.median(mass), rel=1e-10)
    assert report.starved_features[-1] == pytest.approx(np.mean(mass < 0.7))
    c = np.median(expected)
    assert report.implicit_horizon == pytest.approx(1 / (1 - c))


@settings(max_examples=15, deadline=None)
@given(st.integers(2, 8), st.integers(2, 12), st.integers(1, 30), st.floats(0.05, 5.0))
def test_constant_fit_is_the_ridge_fit_of_one_for_any_shape(H, d, K, gamma):
    ds = _dataset(K=K, H=H, d=d, seed=K * 31 + d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StarvedFitWarning)
        report = R2PVI("tv", lam=1.0, gamma=gamma).fit(ds).fit_report_
    expected = [_constant_fit(ds.phi[:, h], gamma) for h in range(H)]
    np.testing.assert_allclose(report.constant_fit, expected, rtol=1e-9)
    assert np.all((report.constant_fit > 0) & (report.constant_fit < 1))


def test_steps_without_an_absorbing_transition_are_counted():
    K, H, d, A = 200, 20, 4, 2
    nv = np.full((K, H, A), np.nan)
    nv[:7, 2] = 0.0            # 7 rows at step 2
    nv[10, 5, 1] = 0.0         # one known action value at step 5
    nv[:3, H - 1] = 0.0        # the last step's next values never enter the fit
    ds = _dataset(K=K, H=H, d=d, next_values=nv)
    with pytest.warns(StarvedFitWarning, match="17 of 19 steps hold no absorbing"):
        report = PEVI().fit(ds).fit_report_
    assert report.absorbing.tolist() == [0, 0, 7, 0, 0, 1] + [0] * 13 + [3]
    assert report.steps_without_absorbing == H - 1 - 2
    assert report.implicit_horizon > H  # the warning is about absorbing steps only
    pooled = PEVI(time_homogeneous=True).fit(ds).fit_report_
    assert pooled.absorbing.tolist() == [8] and pooled.steps_without_absorbing == 0


def test_no_absorbing_warning_when_the_data_holds_none():
    ds = _dataset(K=200, H=20, d=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFitWarning)
        report = PEVI().fit(ds).fit_report_
    assert report.absorbing.sum() == 0 and report.starved() == []


@pytest.mark.parametrize("pooled", [False, True])
def test_no_warning_on_the_simulated_linear_mdp(pooled):
    ds = SimulatedLinearMDP().collect(100)
    estimators = [PEVI(), R2PVI("tv", lam=1.0), R2PVI("kl", lam=1.0), R2PVI("chi2", lam=1.0),
                  DRPVI(rho=0.1)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFitWarning)
        for est in estimators:
            est.set_params(time_homogeneous=pooled)
            assert est.fit(ds).fit_report_.starved() == []


def test_a_short_horizon_never_warns_however_few_the_rows():
    ds = _dataset(K=5, H=10, d=60)
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFitWarning)
        report = PEVI().fit(ds).fit_report_
    assert report.implicit_horizon < 10 / 4  # starved, but H < 20: no warning


def test_the_warning_and_the_report_are_public():
    assert issubclass(StarvedFitWarning, UserWarning)
    assert r2pvi.StarvedFitWarning is StarvedFitWarning
    assert "StarvedFitWarning" in r2pvi.__all__


def test_a_per_step_cartpole_fit_starves_and_the_pooled_one_does_not():
    gym = pytest.importorskip("gymnasium")
    from r2pvi.envs import EpsilonGreedy, collect_episodes
    from r2pvi.episodes import episode_observations
    from r2pvi.features import NormalizedRBF, cross_actions

    def expert(h, obs):
        return (obs[:, 2] + 0.5 * obs[:, 3] > 0).astype(int)

    episodes = collect_episodes(gym.make("CartPole-v1"), EpsilonGreedy(expert, 0.3, 2), 40,
                                seed=0, max_steps=100, n_envs=2, progress=False)
    fmap = cross_actions(NormalizedRBF(n_centers=[1, 1, 5, 5]).fit(
        episode_observations(episodes)), n_actions=2)
    ds = OfflineDataset.from_episodes(episodes, fmap, n_actions=2, horizon=100)
    with pytest.warns(StarvedFitWarning):
        per_step = R2PVI("tv", lam=0.1, beta=0.01, time_homogeneous=False).fit(ds).fit_report_
    assert per_step.implicit_horizon < 25
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFitWarning)
        R2PVI("tv", lam=0.1, beta=0.01, time_homogeneous=True).fit(ds)


@pytest.mark.parametrize("K", [12, 80])
def test_empty_rows_after_an_episode_ends_are_no_transitions(K):
    H, d = 4, 20
    rng = np.random.default_rng(K)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    alive = K // 3
    phi[alive:, 2:] = 0.0  # episodes that ended after step 1: empty rows
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, 2))
    ds = OfflineDataset.from_features(phi, np.zeros((K, H)), next_phi, check_simplex=False)
    report = PEVI().fit(ds).fit_report_
    assert report.rows.tolist() == [K, K, alive, alive]
    expected = [float(np.mean(phi[:n, h] @ np.linalg.solve(
        phi[:, h].T @ phi[:, h] + np.eye(d), phi[:, h].T @ np.ones(K))))
        for h, n in enumerate(report.rows)]
    np.testing.assert_allclose(report.constant_fit, expected, rtol=1e-10)


def test_a_dataset_in_files_records_without_reading_its_files_again(tmp_path):
    K, H, d, A = 300, 20, 6, 2
    nv = np.full((K, H, A), np.nan)
    nv[:5, 3] = 0.0
    ds = _dataset(K=K, H=H, d=d, next_values=nv)
    ds.save(tmp_path / "data")
    on_disk = OfflineDataset.open(tmp_path / "data")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StarvedFitWarning)
        mem = PEVI().fit(ds).fit_report_
        disk = PEVI().fit(on_disk).fit_report_
    # rows on the simplex: E(1) from the Gram factor, no read of the files
    np.testing.assert_allclose(disk.constant_fit, mem.constant_fit, rtol=1e-10)
    np.testing.assert_allclose(disk.feature_mass, mem.feature_mass, rtol=1e-10)
    assert mem.absorbing[3] == 5
    assert disk.absorbing is None or disk.absorbing.tolist() == mem.absorbing.tolist()
    assert disk.summary()
