"""Episodes of a crossed feature map saved as state features (psi once per observation,
actions by index) in a dataset directory: opened over memory maps, loaded, subset, fitted
as in memory; damaged files refused naming the file; readers of version 2 refuse them."""

from __future__ import annotations

import json
import mmap
import shutil
import warnings

import numpy as np
import pytest
from helpers import pooled_or_per_step_estimators
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from r2pvi import PEVI, R2PVI, OfflineDataset
from r2pvi.data.storage import manifest as manifest_module
from r2pvi.data.storage import state_files
from r2pvi.data.storage.crossed import CrossedRows
from r2pvi.features import NormalizedRBF, cross_actions

FAST = settings(max_examples=15, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
FIELDS = ("phi", "rewards", "next_phi", "next_values", "states", "actions", "next_states")


def _episodes(rng, K, max_len=8, obs_dim=2):
    """Episodes of random lengths, terminated (absorbing: known values) or truncated."""
    eps = []
    for _ in range(K):
        T = int(rng.integers(1, max_len + 1))
        term, trunc = np.zeros(T, dtype=bool), np.zeros(T, dtype=bool)
        (term if rng.random() < 0.5 else trunc)[-1] = True
        eps.append({"observations": rng.random((T + 1, obs_dim)),
                    "actions": rng.integers(0, 2, T), "rewards": rng.random(T),
                    "terminations": term, "truncations": trunc})
    return eps


FMAP = cross_actions(NormalizedRBF(n_centers=3).fit(np.array([[0.0, 0.0], [1.0, 1.0]])), 2)


def _dataset(seed=0, K=30, H=6, **kw):
    rng = np.random.default_rng(seed)
    return OfflineDataset.from_episodes(_episodes(rng, K), FMAP, 2, horizon=H, **kw)


def _manifest(path) -> dict:
    return json.loads((path / "manifest.json").read_text())


def _maps_a_file(a: np.ndarray) -> bool:
    """Whether the array's memory is a memory-mapped file (its chain of bases ends in one)."""
    while a is not None and not isinstance(a, mmap.mmap):
        a = getattr(a, "base", None)
    return isinstance(a, mmap.mmap)


# ---------------------------------------------------------------------- round trip
@FAST
@given(K=st.integers(1, 12), H=st.integers(1, 8), offset=st.booleans(),
       f32=st.booleans(), seed=st.integers(0, 2**16))
def test_a_saved_state_layout_opens_and_loads_with_every_field_equal(tmp_path_factory, K, H,
                                                                    offset, f32, seed):
    mem = _dataset(seed, K, H, reward_offset=0.5 if offset else None,
                   dtype="float32" if f32 else None)
    path = mem.save(tmp_path_factory.mktemp("ds") / "d")
    names = sorted(p.name for p in path.iterdir())
    assert "psi.npy" in names and "actions.npy" in names
    assert "phi.npy" not in names and "next_phi.npy" not in names  # not the dense rows
    mf = _manifest(path)
    assert (mf["phi"], mf["next"], mf["format_version"]) == ("state_features",) * 2 + (3,)
    assert np.load(path / "psi.npy").shape == (H + 1, K, 9)
    opened, loaded = OfflineDataset.open(path), OfflineDataset.load(path)
    assert (opened.storage, loaded.storage) == ("disk", "memory")
    idx = np.random.default_rng(seed).integers(0, K, max(1, K // 2))
    for ds in (opened, loaded):
        assert ds.dtype == mem.dtype
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(ds, name), getattr(mem, name), err_msg=name)
        sub = ds.subset(idx)
        assert sub.storage == "memory"
        for name in ("phi", "next_phi", "next_values", "rewards"):
            np.testing.assert_array_equal(getattr(sub, name), getattr(mem.subset(idx), name))
        assert ds.reward_range == mem.reward_range
        assert ds.stationary and ds._source.reward_offset == mem._source.reward_offset
        assert ds.nonnegative_features == mem.nonnegative_features
        assert ds.nonnegative_next_features == mem.nonnegative_next_features


def test_pooled_rows_of_an_opened_dataset_read_the_memory_mapped_file(tmp_path):
    opened = OfflineDataset.open(_dataset().save(tmp_path / "d"))
    phi, _, nxt, _ = opened._source.pooled(opened.horizon - 1)
    assert isinstance(phi, CrossedRows) and isinstance(nxt, CrossedRows)
    assert _maps_a_file(phi.psi) and _maps_a_file(nxt.psi) and _maps_a_file(phi.actions)


ESTIMATORS = pooled_or_per_step_estimators()[:5]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Longer episodes (H = 10) in memory, saved as float64 and as float32."""
    root = tmp_path_factory.mktemp("saved")
    mem = _dataset(3, K=40, H=10, reward_offset=0.5)
    return mem, mem.save(root / "f64"), mem.save(root / "f32", dtype="float32")


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("make", ESTIMATORS)
@pytest.mark.parametrize("pooled", [False, True])
def test_fits_from_the_directory_equal_fits_in_memory(saved, make, pooled):
    mem, path, _ = saved
    want = make(pooled).fit(mem).weights_
    for ds in (OfflineDataset.open(path), OfflineDataset.load(path)):
        got = make(pooled).fit(ds).weights_
        if pooled:
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
        else:  # the same rows read the same way: the same bits
            np.testing.assert_array_equal(got, want)
    idx = np.arange(0, 40, 3)
    np.testing.assert_allclose(make(pooled).fit(OfflineDataset.open(path).subset(idx)).weights_,
                               make(pooled).fit(mem.subset(idx)).weights_, rtol=1e-10,
                               atol=1e-10)


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("pooled", [False, True])
def test_a_float32_save_stores_rounded_state_features_and_fits_like_float32_in_memory(
        saved, pooled):
    mem, _, path = saved
    opened = OfflineDataset.open(path)
    assert opened.dtype == np.float32 and _manifest(path)["dtype"] == "float32"
    np.testing.assert_array_equal(np.load(path / "psi.npy"),
                                  mem._source.phi.psi.astype(np.float32))
    rng = np.random.default_rng(3)  # the same episodes, built in float32
    f32 = OfflineDataset.from_episodes(_episodes(rng, 40), FMAP, 2, horizon=10,
                                       reward_offset=0.5, dtype="float32")
    est = R2PVI("kl", lam=0.5, beta=0.1, r_max=1.5, time_homogeneous=pooled)
    a, b = est.fit(opened).weights_, est.fit(f32).weights_
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a, est.fit(mem).weights_, rtol=1e-5, atol=1e-5)


def test_a_resaved_opened_dataset_is_the_same_directory(saved, tmp_path):
    _, path, _ = saved
    again = OfflineDataset.open(path).save(tmp_path / "again")
    assert _manifest(again) == _manifest(path)
    for name in ("psi", "actions", "rewards", "next_values"):
        np.testing.assert_array_equal(np.load(again / f"{name}.npy"),
                                      np.load(path / f"{name}.npy"))


def test_the_behaviour_form_is_refused_for_state_features(tmp_path):
    with pytest.raises(ValueError, match="state features once per observation"):
        _dataset().save(tmp_path / "d", next_form="behaviour")
    assert not (tmp_path / "d").exists()


# ---------------------------------------------------------------------- older readers
def test_a_reader_of_format_version_2_refuses_state_features_asking_for_an_upgrade(
        saved, monkeypatch):
    _, path, _ = saved
    monkeypatch.setattr(manifest_module, "FORMAT_VERSION", 2)  # what r2pvi 2's reader checks
    with pytest.raises(ValueError, match="format version 3.*upgrade r2pvi"):
        OfflineDataset.open(path)


def test_datasets_of_the_other_kinds_are_still_written_as_version_2(tmp_path):
    dense = OfflineDataset.from_episodes(_episodes(np.random.default_rng(0), 5),
                                         lambda o, a: FMAP(o, a), 2, horizon=4)
    assert _manifest(dense.save(tmp_path / "d"))["format_version"] == 2


# ---------------------------------------------------------------------- damaged files
def _copy(saved, tmp_path, which=1):
    return shutil.copytree(saved[which], tmp_path / "ds")


def _refused(path, *names, fit=False):
    with pytest.raises(ValueError) as info:
        ds = OfflineDataset.open(path)
        if fit:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                PEVI(beta=0.1, r_max=1.5, time_homogeneous=True).fit(ds)
    msg = str(info.value)
    for name in names:
        assert str(name) in msg, (name, msg)
    return msg


def _edit(path, name, fn):
    arr = np.load(path / f"{name}.npy")
    np.save(path / f"{name}.npy", fn(arr.copy()), allow_pickle=False)


@FAST
@given(data=st.data())
def test_a_non_finite_state_feature_is_refused_naming_the_file_and_its_index(
        saved, tmp_path_factory, monkeypatch, data):
    monkeypatch.setattr(state_files, "_SCAN_ROWS", data.draw(st.integers(1, 64)))
    path = _copy(saved, tmp_path_factory.mktemp("nan"))
    t, k, j = (data.draw(st.integers(0, n - 1)) for n in (11, 40, 9))
    bad = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))

    def put(a):
        a[t, k, j] = bad
        return a

    _edit(path, "psi", put)
    msg = _refused(path, path / "psi.npy", f"at index [{t}, {k}, {j}]",
                   f"observation {t}, trajectory {k}, feature {j}", "write the dataset again")
    assert "a non-finite number" in msg


@pytest.mark.parametrize("value", [2, -2, 100])
def test_an_action_index_out_of_range_is_refused_naming_the_file(saved, tmp_path, value):
    path = _copy(saved, tmp_path)

    def put(a):
        a[4, 7] = value
        return a

    _edit(path, "actions", put)
    _refused(path, path / "actions.npy", f"holds {value} at index [4, 7]", "n_actions = 2")


def test_an_infinite_known_value_is_refused_naming_next_values(saved, tmp_path):
    path = _copy(saved, tmp_path)

    def put(a):
        a[1, 2, 0] = np.inf
        return a

    _edit(path, "next_values", put)
    _refused(path, path / "next_values.npy", "infinite known value", "at index [1, 2, 0]")


@pytest.mark.parametrize("name, edit, words", [
    ("psi", lambda a: a[:-1], ["psi.npy", "has shape (10, 40, 9)", "[11, 40, 9]"]),
    ("psi", lambda a: a.astype(np.float32), ["psi.npy", "float32", "float64"]),
    ("actions", lambda a: a.astype(np.float64), ["actions.npy", "integer"]),
    ("actions", lambda a: a[:, :-1], ["actions.npy", "has shape (10, 39)"]),
])
def test_a_file_of_a_wrong_shape_or_type_is_refused_naming_it(saved, tmp_path, name, edit,
                                                              words):
    path = _copy(saved, tmp_path)
    _edit(path, name, edit)
    _refused(path, *words)


def test_a_missing_state_feature_file_is_named(saved, tmp_path):
    path = _copy(saved, tmp_path)
    (path / "psi.npy").unlink()
    _refused(path, path / "psi.npy", "is missing")


@pytest.mark.parametrize("edit, words", [
    (lambda m: m.update(next="stored"), ["'phi'", "must be 'state_features' too"]),
    (lambda m: m.update(phi="stored"), ["'next'", "must be 'state_features' too"]),
    (lambda m: m.pop("n_state_features"), ["n_state_features", "integer >= 1"]),
    (lambda m: m.update(n_state_features=4), ["n_features", "2 x 4 = 8"]),
    (lambda m: m.update(format_version=2), ["format_version", "have format version 3"]),
    (lambda m: m["shapes"].update(psi=[10, 40, 9]), ["shapes.psi", "(11, 40, 9)"]),
    (lambda m: m["files"].pop("actions"), ["files.actions", "is missing"]),
])
def test_a_hand_edited_state_manifest_is_refused_naming_the_key(saved, tmp_path, edit, words):
    path = _copy(saved, tmp_path)
    mf = _manifest(path)
    edit(mf)
    (path / "manifest.json").write_text(json.dumps(mf))
    _refused(path, path / "manifest.json", *words)


def test_one_fit_of_an_opened_directory_checks_the_rewards_it_reads(saved, tmp_path):
    """docs/storage.md, "Verify": opening checks the structure and the state features; one
    PEVI fit checks the rewards."""
    path = _copy(saved, tmp_path)

    def put(a):
        a[2, 5] = 7.0
        return a

    _edit(path, "rewards", put)
    OfflineDataset.open(path)  # the rewards are checked by the fit
    _refused(path, path / "rewards.npy", "at index [2, 5]", fit=True)
