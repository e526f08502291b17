"""A fit never uses a non-finite number or a reward outside [0, r_max], whatever the source:
dataset directories whose files changed after they were written, Dask arrays, features
computed by a feature map. The error names the file (or the field), the step, the first bad
index and the fix."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.algorithms import DRPVI

K, H, D, A = 24, 3, 4, 2


def _data(seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(D), (K, H))
    nphi = rng.dirichlet(np.ones(D), (K, H, A))
    rewards = rng.uniform(0.05, 0.95, (K, H))
    return phi, rewards, nphi


def _saved(path, dtype="float64", next_form="full", next_values=None):
    phi, rewards, nphi = _data()
    OfflineDataset.from_features(phi, rewards, nphi, next_values).save(
        path, dtype=dtype, next_form=next_form)
    return path


def _damage(path, name, index, value):
    """Write ``value`` at ``index`` of the saved file ``name`` (dtype and shape kept)."""
    a = np.load(path / name, mmap_mode="r+")
    a[index] = value
    a.flush()
    del a


def _refused(path, name, index, fit, *context):
    """The fit raises a ValueError naming the file, the index and the fix."""
    where = re.escape(f"{path / name}") + r".*" + re.escape(f"at index {list(index)}")
    with pytest.raises(ValueError, match=where) as info:
        fit()
    msg = str(info.value)
    assert "write the dataset again" in msg
    for c in context:
        assert c in msg
    return msg


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
@pytest.mark.parametrize("name, index, where", [
    ("phi.npy", (1, 5, 2), "step 1, trajectory 5, feature 2"),
    ("rewards.npy", (1, 5), "step 1, trajectory 5"),
    ("next_phi.npy", (0, 7, 1, 3), "step 0, trajectory 7, action 1, feature 3"),
])
def test_a_fit_refuses_nan_or_inf_written_into_a_saved_file(tmp_path, dtype, value, name,
                                                            index, where):
    path = _saved(tmp_path / "ds", dtype)
    _damage(path, name, index, value)
    ds = OfflineDataset.open(path)
    _refused(path, name, index, lambda: R2PVI("tv", 0.5).fit(ds), where)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_negative_reward_written_into_rewards_npy_is_refused_despite_the_manifest(
        tmp_path, dtype):
    """The manifest's reward_range is out of date: the fit checks the rewards it reads."""
    path = _saved(tmp_path / "ds", dtype)
    _damage(path, "rewards.npy", (2, 3), -0.5)
    ds = OfflineDataset.open(path)
    msg = _refused(path, "rewards.npy", (2, 3), lambda: R2PVI("tv", 0.5).fit(ds),
                   "-0.5", "r_max=1.0", "manifest records reward_range")
    assert "step 2, trajectory 3" in msg
    _damage(path, "rewards.npy", (2, 3), 1.5)  # above r_max
    with pytest.raises(ValueError, match="1.5.*outside"):
        R2PVI("kl", 0.5).fit(OfflineDataset.open(path))


def test_rewards_within_the_declared_noise_pass_and_beyond_it_are_refused(tmp_path):
    phi, rewards, nphi = _data()
    OfflineDataset.from_features(phi, rewards, nphi, reward_noise=0.1).save(tmp_path / "ds")
    path = tmp_path / "ds"
    _damage(path, "rewards.npy", (1, 1), -0.7)  # 7 standard deviations: noise
    R2PVI("tv", 0.5).fit(OfflineDataset.open(path))
    _damage(path, "rewards.npy", (1, 1), -0.9)  # 9: not noise
    with pytest.raises(ValueError, match=r"-0\.9.*reward_noise=0\.1"):
        R2PVI("tv", 0.5).fit(OfflineDataset.open(path))


@pytest.mark.parametrize("value", [np.nan, np.inf])
@pytest.mark.parametrize("name, index", [("phi_sums.npy", (1, 2)), ("gram.npy", (1, 2, 2))])
def test_non_finite_stored_sums_are_refused_when_the_dataset_is_opened(tmp_path, value, name,
                                                                       index):
    """KL takes E(1) from phi_sums.npy and every fit Lambda from gram.npy: a damaged one
    would shift the weights (KL by 2.7e-3) or make them NaN."""
    path = _saved(tmp_path / "ds")
    _damage(path, name, index, value)
    msg = _refused(path, name, index, lambda: OfflineDataset.open(path), "step 1")
    assert repr(float(value)) in msg


@pytest.mark.parametrize("value", [np.nan, np.inf])
@pytest.mark.parametrize("field, index, where", [
    ("phi", (5, 1, 2), "step 1, trajectory 5, feature 2"),
    ("rewards", (5, 1), "step 1, trajectory 5"),
    ("next_phi", (9, 0, 1, 0), "step 0, trajectory 9, action 1, feature 0"),
])
def test_a_fit_of_dask_arrays_refuses_nan_or_inf(field, index, where, value):
    da = pytest.importorskip("dask.array")
    arrays = dict(zip(("phi", "rewards", "next_phi"), _data(), strict=True))
    arrays[field] = arrays[field].copy()
    arrays[field][index] = value
    ds = OfflineDataset.from_dask(*(da.from_array(arrays[k], chunks=(8,) + arrays[k].shape[1:])
                                    for k in ("phi", "rewards", "next_phi")))
    with pytest.raises(ValueError, match=re.escape(f"{field} (a Dask array) holds {value!r}")
                       ) as e:
        R2PVI("tv", 0.5).fit(ds)
    assert where in str(e.value) and "from_features" in str(e.value)


@pytest.mark.parametrize("which", ["states", "next_states"])
def test_a_fit_refuses_a_feature_map_that_returns_nan(which):
    rng = np.random.default_rng(1)
    obs, nobs = rng.random((K, H, 1)), rng.random((K, H, 1))
    bad = (obs if which == "states" else nobs)[6, 0, 0]

    def fmap(x, a):
        out = np.stack([x[:, 0] * (a == 0), x[:, 0] * (a == 1), 1 - x[:, 0]], axis=1)
        out[x[:, 0] == bad, 1] = np.nan
        return out

    ds = OfflineDataset.from_observations(obs, rng.integers(A, size=(K, H)),
                                          rng.random((K, H)), nobs, fmap, A,
                                          check_simplex=False)
    what = "taken-action features" if which == "states" else "next observations"
    with pytest.raises(ValueError, match=f"feature_map returned nan for the .*{what}") as e:
        R2PVI("tv", 0.5).fit(ds)
    assert "trajectory 6" in str(e.value) and "feature 1" in str(e.value)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A saved float32 dataset and its clean TV and PEVI weights."""
    path = _saved(tmp_path_factory.mktemp("clean") / "ds", "float32")
    ds = OfflineDataset.open(path)
    return path, {"tv": R2PVI("tv", 0.5).fit(ds).weights_, "pevi": PEVI().fit(ds).weights_}


FILES = {"phi.npy": (H, K, D), "rewards.npy": (H, K), "next_phi.npy": (H, K, A, D)}


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(FILES)), est=st.sampled_from(["tv", "pevi"]),
       value=st.sampled_from([np.nan, np.inf, -np.inf]), data=st.data())
def test_any_single_non_finite_entry_is_named_or_never_used(clean, tmp_path, name, est, value,
                                                            data):
    """Every entry a fit uses is checked and named exactly; the only entries it may leave
    alone are those it never reads (the next states of the last step: V_H = 0), and then its
    weights are the clean ones."""
    src, weights = clean
    index = tuple(data.draw(st.integers(0, n - 1)) for n in FILES[name])
    path = tmp_path / f"ds-{name}-{'-'.join(map(str, index))}-{est}-{value}"
    shutil.rmtree(path, ignore_errors=True)
    shutil.copytree(src, path)
    _damage(path, name, index, value)
    fit = lambda: (R2PVI("tv", 0.5) if est == "tv" else PEVI()).fit(  # noqa: E731
        OfflineDataset.open(path)).weights_
    if name == "next_phi.npy" and index[0] == H - 1:
        np.testing.assert_array_equal(fit(), weights[est])
    else:
        _refused(path, name, index, fit)


def test_the_behaviour_form_names_the_file_a_bad_next_state_row_came_from(tmp_path):
    """Next-state rows rebuilt from the next step's features, the side table or the other
    actions' rows: the error names the file and the index in it."""
    phi, rewards, nphi = _data()
    nphi[:, :-1, 0] = phi[:, 1:]  # action 0 leads to the next step's taken action
    OfflineDataset.from_features(phi, rewards, nphi).save(tmp_path / "b", next_form="behaviour")
    path = tmp_path / "b"
    _damage(path, "next_rest.npy", (0, 4, 0, 1), np.inf)  # action 1's row of sample (0, 4)
    msg = _refused(path, "next_rest.npy", (0, 4, 0, 1),
                   lambda: R2PVI("tv", 0.5).fit(OfflineDataset.open(path)))
    assert "step 0, trajectory 4, action 1, feature 1" in msg


def test_known_values_files_may_hold_nan_but_not_infinities(tmp_path):
    phi, rewards, nphi = _data()
    nv = np.full((K, H, A), np.nan)
    nv[::5, :, 1] = 0.25
    OfflineDataset.from_features(phi, rewards, nphi, nv).save(tmp_path / "kv")
    path = tmp_path / "kv"
    _damage(path, "next_phi.npy", (0, 5, 1, 0), np.nan)  # known value there: not used
    R2PVI("tv", 0.5).fit(OfflineDataset.open(path))
    _damage(path, "next_values.npy", (0, 10, 1), -np.inf)
    _refused(path, "next_values.npy", (0, 10, 1),
             lambda: R2PVI("tv", 0.5).fit(OfflineDataset.open(path)),
             "step 0, trajectory 10, action 1")


def test_a_damaged_next_state_table_is_refused_when_the_dataset_is_opened(tmp_path):
    rng = np.random.default_rng(2)
    table = rng.dirichlet(np.ones(D), (5, A))
    idx = rng.integers(5, size=(K, H))
    ds = OfflineDataset.from_next_state_table(table[idx, 0], rng.random((K, H)), idx, table)
    ds.save(tmp_path / "t")
    path = tmp_path / "t"
    _damage(path, "next_table.npy", (3, 1, 2), np.nan)
    _refused(path, "next_table.npy", (3, 1, 2), lambda: OfflineDataset.open(path))


@pytest.mark.parametrize("value", [np.nan, np.inf])
@pytest.mark.parametrize("how", ["pooled", "dual", "chi2", "reward_weights", "row_sums"])
def test_every_fit_path_refuses_a_non_finite_feature_file(tmp_path, how, value):
    """Pooled steps, the dual form, rules that hold a step's rows (chi^2), known
    reward_weights (checked on the data by a product when the recorded row sums do not
    settle them): the same error."""
    path = _saved(tmp_path / "ds")
    _damage(path, "phi.npy", (0, 3, 1), value)
    theta = np.full((H, D), 0.5)
    est = {"pooled": lambda: R2PVI("tv", 0.5, time_homogeneous=True),
           "dual": lambda: R2PVI("tv", 0.5),
           "chi2": lambda: R2PVI("chi2", 0.5),
           "reward_weights": lambda: DRPVI(0.1, reward_weights=theta),
           "row_sums": lambda: DRPVI(0.1, reward_weights=theta)}[how]()
    if how == "dual":
        est._gram_form = "dual"
    if how in ("row_sums", "chi2"):  # drop a record of the manifest, as a user may
        mf = json.loads((path / "manifest.json").read_text())
        if how == "row_sums":  # no row-sum range: the reward check reads the features
            del mf["phi_row_sums"]
        else:  # no stored Gram matrix: formed from the rows held in memory
            del mf["files"]["gram"]
            (path / "gram.npy").unlink()
        (path / "manifest.json").write_text(json.dumps(mf))
    ds = OfflineDataset.open(path)
    _refused(path, "phi.npy", (0, 3, 1), lambda: est.fit(ds), "step 0, trajectory 3")


def test_rows_loaded_or_selected_from_a_directory_are_checked_by_the_fit(tmp_path):
    path = _saved(tmp_path / "ds")
    _damage(path, "next_phi.npy", (1, 2, 0, 0), np.inf)
    for ds in (OfflineDataset.load(path), OfflineDataset.open(path).subset(np.arange(K))):
        with pytest.raises(ValueError, match=re.escape(str(path / "next_phi.npy"))
                           + r" \(selected trajectories\) holds inf"):
            R2PVI("tv", 0.5).fit(ds)


@pytest.mark.parametrize("source", ["directory", "dask"])
@pytest.mark.parametrize("field", ["phi", "next_phi"])
def test_an_infinity_beside_zeros_is_named_not_warned(tmp_path, source, field):
    """One-hot rows and zero weights: ``inf * 0`` is NaN and warns; the fit names the entry
    instead (the suite turns RuntimeWarnings into errors)."""
    rng = np.random.default_rng(4)
    phi = np.eye(D)[rng.integers(D, size=(K, H))]
    nphi = np.eye(D)[rng.integers(D, size=(K, H, A))]
    rewards = np.where(rng.random((K, H)) < 0.5, 0.0, 0.5)
    index = (5, 1, 3) if field == "phi" else (5, 0, 1, 3)
    arrays = {"phi": phi, "rewards": rewards, "next_phi": nphi}
    arrays[field][index] = -np.inf
    if source == "dask":
        da = pytest.importorskip("dask.array")
        ds = OfflineDataset.from_dask(*(da.from_array(arrays[k], chunks=(8,) + arrays[k].shape[1:])
                                        for k in ("phi", "rewards", "next_phi")))
    else:
        arrays[field][index] = 0.0
        OfflineDataset.from_features(phi, rewards, nphi).save(tmp_path / "ds")
        _damage(tmp_path / "ds", f"{field}.npy", (index[1], index[0]) + index[2:], -np.inf)
        ds = OfflineDataset.open(tmp_path / "ds")
    theta = np.zeros((H, D))
    for est in (R2PVI("tv", 0.5), R2PVI("tv", 0.5, reward_weights=theta), R2PVI("chi2", 0.5)):
        with pytest.raises(ValueError, match=r"holds -inf.*trajectory 5"):
            est.fit(ds)


def _fmap(x, a):
    x = np.asarray(x, dtype=float).reshape(len(x), -1)
    return np.stack([x[:, 0] * (a == 0), x[:, 0] * (a == 1), 1 - x[:, 0]], axis=1)


@pytest.mark.parametrize("which", ["states", "next_states"])
def test_stored_observations_must_be_finite_and_rectangular(which):
    rng = np.random.default_rng(3)
    args = {"states": rng.random((20, 3, 1)), "actions": rng.integers(2, size=(20, 3)),
            "rewards": rng.random((20, 3)), "next_states": rng.random((20, 3, 1))}
    args[which][4, 1, 0] = np.nan
    with pytest.raises(ValueError, match=re.escape(f"{which}[4, 1]")):
        OfflineDataset.from_observations(feature_map=_fmap, n_actions=2, **args)
    args[which] = [[0.1], [0.2, 0.3]]
    with pytest.raises(ValueError, match=f"{which} must be a rectangular array"):
        OfflineDataset.from_observations(feature_map=_fmap, n_actions=2, **args)
