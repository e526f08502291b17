"""Every damaged or hand-edited file is a ValueError naming the file and the field (never a
KeyError, an AttributeError, NumPy's allow_pickle advice, or a silent read), and bad arguments
of the public constructors name the argument."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from storage_helpers import small_arrays

import r2pvi
from r2pvi import DRVIL, PEVI, R2PVI, OfflineDataset
from r2pvi.sparse import SparseOfflineDataset

K, H, A, D = 20, 3, 2, 4


def _data(seed=0, known=False):
    rng = np.random.default_rng(seed)
    nv = None
    if known:
        nv = np.full((K, H, A), np.nan)
        nv[:4, :, 1] = 0.5
    return OfflineDataset.from_features(rng.dirichlet(np.ones(D), (K, H)), rng.random((K, H)),
                                        rng.dirichlet(np.ones(D), (K, H, A)), nv,
                                        states=rng.random((K, H, 2)))


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    return _data(known=True).save(tmp_path_factory.mktemp("tpl") / "ds")


def _copy(template, tmp_path) -> Path:
    return Path(shutil.copytree(template, tmp_path / "ds"))


def _manifest(path) -> dict:
    return json.loads((path / "manifest.json").read_text())


def _write_manifest(path, mf) -> None:
    (path / "manifest.json").write_text(json.dumps(mf))


def _open_and_fit(path, **kw):
    return R2PVI("tv", lam=0.5).fit(OfflineDataset.open(path, **kw))


def _refused(path, *names, fit=True, **kw):
    """Opening (and fitting) ``path`` raises a ValueError whose message names each of
    ``names``; returns the message."""
    with pytest.raises(ValueError) as info:
        _open_and_fit(path, **kw) if fit else OfflineDataset.open(path, **kw)
    msg = str(info.value)
    for name in names:
        assert str(name) in msg, (name, msg)
    assert "allow_pickle" not in msg
    return msg


# ---------------------------------------------------------------- the manifest
@pytest.mark.parametrize("bad", [0, 1, -3, 2.0, "2", True, None])
def test_damaged_format_versions_are_refused_with_the_right_advice(tmp_path, bad):
    """A format version that is not an integer >= 2 is damage, not a newer format: refused,
    and the message does not advise upgrading r2pvi."""
    path = OfflineDataset.from_features(*small_arrays(3)).save(tmp_path / "d")
    mf = json.loads((path / "manifest.json").read_text())
    (path / "manifest.json").write_text(json.dumps({**mf, "format_version": bad}))
    with pytest.raises(ValueError, match="must be an integer >= 2") as err:
        OfflineDataset.open(path)
    assert "upgrade" not in str(err.value)


@pytest.mark.parametrize("key", ["files", "shapes", "next", "horizon", "n_features",
                                 "n_actions", "n_trajectories"])
def test_a_manifest_missing_a_key_names_the_manifest_and_the_key(template, tmp_path, key):
    path = _copy(template, tmp_path)
    mf = _manifest(path)
    del mf[key]
    _write_manifest(path, mf)
    _refused(path, path / "manifest.json", f"'{key}' is missing")


@pytest.mark.parametrize("text, what", [
    ("", "is empty"), ("{kind: r2pvi", "is not valid JSON"), ("[1, 2]", "JSON object, got a "
                                                                          "JSON list"),
    ('"dataset"', "JSON object, got a JSON str")])
def test_an_empty_or_non_object_manifest_names_its_path(template, tmp_path, text, what):
    path = _copy(template, tmp_path)
    (path / "manifest.json").write_text(text)
    _refused(path, path / "manifest.json", what)


@pytest.mark.parametrize("key, bad", [
    ("horizon", -1), ("n_features", 2.5), ("n_actions", True), ("next", "bogus"),
    ("phi", "computed"), ("extras", "states"), ("nonnegative_phi", "yes"),
    ("dtype", "float16"), ("files", ["phi.npy"]), ("shapes", None)])
def test_a_manifest_key_of_a_wrong_type_or_range_names_the_key(template, tmp_path, key, bad):
    path = _copy(template, tmp_path)
    _write_manifest(path, {**_manifest(path), key: bad})
    _refused(path, path / "manifest.json", key)


@pytest.mark.parametrize("where", ["../outside/phi.npy", "absolute", "sub/phi.npy"])
def test_files_outside_the_dataset_directory_are_refused(template, tmp_path, where):
    path = _copy(template, tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copy(path / "phi.npy", outside / "phi.npy")  # a valid file: reading it is silent
    target = str(outside / "phi.npy") if where == "absolute" else where
    mf = _manifest(path)
    mf["files"]["phi"] = target
    _write_manifest(path, mf)
    _refused(path, "files.phi", "inside", "r2pvi reads no file outside")


def test_next_table_without_its_files_names_the_missing_field(template, tmp_path):
    path = _copy(template, tmp_path)
    _write_manifest(path, {**_manifest(path), "next": "table"})
    _refused(path, "manifest.json", "files.next_phi")  # a field the table form does not have
    mf = _manifest(path)
    del mf["files"]["next_phi"]
    _write_manifest(path, mf)
    _refused(path, "manifest.json", "files.next_index", "is missing")


def test_a_gram_entry_pointing_at_an_npz_names_the_file(template, tmp_path):
    path = _copy(template, tmp_path)
    np.savez(path / "gram.npz", gram=np.load(path / "gram.npy"))
    mf = _manifest(path)
    mf["files"]["gram"] = "gram.npz"
    _write_manifest(path, mf)
    _refused(path, path / "gram.npz", "'gram'", "not a .npy file")


# ---------------------------------------------------------------- the .npy files
_NPY = ["phi.npy", "rewards.npy", "next_phi.npy", "next_values.npy", "gram.npy",
        "phi_sums.npy", "extra_states.npy"]


@pytest.mark.parametrize("name", _NPY)
def test_an_empty_npy_file_names_the_file(template, tmp_path, name):
    path = _copy(template, tmp_path)
    (path / name).write_bytes(b"")
    _refused(path, path / name, "is empty")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.data_too_large])
@given(name=st.sampled_from(_NPY), data=st.data())
def test_garbage_or_a_truncation_of_any_npy_file_names_the_file(template, name, data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(shutil.copytree(template, Path(tmp) / "ds"))
        raw = (path / name).read_bytes()
        if data.draw(st.booleans(), label="truncate"):
            cut = data.draw(st.integers(0, len(raw) - 1), label="keep")
            (path / name).write_bytes(raw[:cut])
        else:
            (path / name).write_bytes(data.draw(st.binary(min_size=1, max_size=len(raw)),
                                                label="garbage"))
        _refused(path, path / name)


@pytest.mark.parametrize("name, content, what", [
    ("gram.npy", lambda a: a.astype(np.float32), "float32"),
    ("phi.npy", lambda a: a.astype(np.int64), "int64"),
    ("rewards.npy", lambda a: a[:, :-1], "shape"),
    ("next_phi.npy", lambda a: np.asfortranarray(a), "Fortran"),
])
def test_a_npy_file_of_a_wrong_dtype_shape_or_order_names_the_file(template, tmp_path, name,
                                                                   content, what):
    path = _copy(template, tmp_path)
    np.save(path / name, content(np.load(path / name)))
    _refused(path, path / name, what)


def test_an_object_array_header_is_refused_without_the_pickle_advice(template, tmp_path):
    path = _copy(template, tmp_path)
    with open(path / "phi_sums.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "|O", "fortran_order": False,
                                                  "shape": (H, D)})
        fh.write(b"\x80\x04K\x01." * 20)
    _refused(path, path / "phi_sums.npy", "Python objects")


@pytest.mark.parametrize("damage", ["negated", "asymmetric", "not PSD", "NaN"])
def test_a_damaged_gram_matrix_is_blamed_on_the_file_not_on_collinear_features(
        template, tmp_path, damage):
    path = _copy(template, tmp_path)
    g = np.load(path / "gram.npy")
    if damage == "negated":
        g = -g
    elif damage == "asymmetric":
        g[0, 0, 1] += 0.5 * g[0, 0, 0]
    elif damage == "not PSD":  # symmetric, within Cauchy-Schwarz, one negative eigenvalue
        w, v = np.linalg.eigh(g[1])
        w[0] = -0.5 * w[-1]
        g[1] = (v * w) @ v.T
    else:
        g[2, 1, 1] = np.nan
    np.save(path / "gram.npy", g)
    msg = _refused(path, path / "gram.npy", "'gram'")
    assert "collinear" not in msg
    assert "damaged" in msg


def test_negative_column_sums_of_non_negative_features_name_phi_sums(template, tmp_path):
    path = _copy(template, tmp_path)
    np.save(path / "phi_sums.npy", -np.load(path / "phi_sums.npy"))
    _refused(path, path / "phi_sums.npy", "'phi_sums'", "damaged")


def test_a_table_index_outside_the_table_names_next_index(tmp_path):
    rng = np.random.default_rng(0)
    table = rng.dirichlet(np.ones(D), (5, A))
    ds = OfflineDataset.from_next_state_table(rng.dirichlet(np.ones(D), (K, H)),
                                              rng.random((K, H)), rng.integers(5, size=(K, H)),
                                              table)
    path = ds.save(tmp_path / "t")
    idx = np.load(path / "next_index.npy")
    idx[0, 3] = 7
    np.save(path / "next_index.npy", idx)
    _refused(path, "next_index[h=0, k=3] = 7", "5-state")


def test_a_map_dataset_names_a_manifest_that_disagrees_with_the_feature_map(tmp_path):
    from r2pvi.features import StateAggregation, cross_actions

    rng = np.random.default_rng(0)
    obs = rng.random((K, H, 1))
    fmap = cross_actions(StateAggregation(n_bins=2).fit(obs.reshape(-1, 1)), n_actions=A)
    ds = OfflineDataset.from_observations(obs, rng.integers(A, size=(K, H)),
                                          rng.random((K, H)), obs, fmap, A)
    path = ds.save(tmp_path / "m")
    for key, value in (("n_features", 2 * A + 1), ("n_actions", A + 1)):
        mf = _manifest(path)
        good = mf[key]
        _write_manifest(path, {**mf, key: value})
        _refused(path, "manifest", key, "feature map", fit=False, feature_map=fmap)
        _write_manifest(path, {**mf, key: good})
    assert OfflineDataset.open(path, feature_map=fmap).n_features == 2 * A


# ---------------------------------------------------------------- model and feature-map files
@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    data = _data()
    rng = np.random.default_rng(1)
    wide = OfflineDataset.from_features(rng.dirichlet(np.ones(30), (6, H)), rng.random((6, H)),
                                        rng.dirichlet(np.ones(30), (6, H, A)))
    return {"primal": PEVI(gamma=0.5).fit(data).save(root / "primal.npz"),
            "dual": PEVI(gamma=0.5).fit(wide).save(root / "dual.npz")}


def _edit_model(src, dst, arrays=None, header=None):
    with np.load(src, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    meta = json.loads(str(members["__r2pvi_meta__"]))
    members.update(arrays or {})
    meta.update(header or {})
    members["__r2pvi_meta__"] = np.array(json.dumps(meta))
    np.savez(dst, **{k: v for k, v in members.items() if v is not None})
    return dst


@pytest.mark.parametrize("form, edit, field", [
    ("primal", lambda z: {"elliptical_c": -np.abs(z["elliptical_c"]) - 1}, "elliptical_c"),
    ("primal", lambda z: {"elliptical_c": 2 * z["elliptical_c"]}, "elliptical_c"),
    ("dual", lambda z: {"elliptical_c": 3 * z["elliptical_c"]}, "elliptical_c"),
    ("dual", lambda z: {"elliptical_r": 5 * z["elliptical_r"]}, "elliptical_r"),
    ("primal", lambda z: {"elliptical_r": z["elliptical_r"].transpose(0, 2, 1)}, "elliptical_r"),
    ("primal", lambda z: {"gram_inv_diag_": 10 * z["gram_inv_diag_"]}, "gram_inv_diag_"),
    ("primal", lambda z: {"weights_": np.where(np.arange(z["weights_"].size).reshape(
        z["weights_"].shape) == 2, np.nan, z["weights_"])}, "weights_"),
    ("primal", lambda z: {"reward_weights_": z["reward_weights_"][:, :-1]}, "reward_weights_"),
])
def test_a_hand_edited_model_file_is_refused_naming_the_field(models, tmp_path, form, edit,
                                                               field):
    with np.load(models[form], allow_pickle=False) as z:
        bad = _edit_model(models[form], tmp_path / "bad.npz", edit(z))
    with pytest.raises(ValueError, match=field) as info:
        r2pvi.load(bad)
    assert str(bad) in str(info.value)


@pytest.mark.parametrize("header, field", [
    ({"elliptical_kinds": None}, "elliptical_kinds"),
    ({"params": {"beta": 1.0, "gamma": 0.5, "penalty": "elliptical", "r_max": 1.0,
                 "reward_weights": None, "time_homogeneous": "bogus"}}, "time_homogeneous"),
])
def test_a_model_header_with_a_bad_field_is_refused(models, tmp_path, header, field):
    with np.load(models["primal"], allow_pickle=False) as z:
        meta = json.loads(str(z["__r2pvi_meta__"]))
    meta.update(header)
    meta = {k: v for k, v in meta.items() if v is not None}
    bad = _edit_model(models["primal"], tmp_path / "bad.npz")
    with np.load(bad) as z:
        members = {k: z[k] for k in z.files}
    members["__r2pvi_meta__"] = np.array(json.dumps(meta))
    np.savez(bad, **members)
    with pytest.raises(ValueError, match=field):
        r2pvi.load(bad)


def test_a_feature_map_file_with_altered_fitted_values_is_refused(tmp_path):
    from r2pvi.features import NormalizedRBF, cross_actions, load_feature_map

    X = np.random.default_rng(0).normal(size=(50, 2))
    path = cross_actions(NormalizedRBF(n_centers=3).fit(X), n_actions=A).save(tmp_path / "f.npz")
    assert load_feature_map(path).n_actions == A
    for name, value in (("state_fitted_sigma_", lambda v: np.full(v.shape, np.nan)),
                        ("state_fitted_centers_", lambda v: v + 0.25),
                        ("state_fitted_high_", lambda v: v - 100.0)):
        with np.load(path, allow_pickle=False) as z:
            members = {k: z[k] for k in z.files}
        members[name] = value(members[name])
        np.savez(tmp_path / "bad.npz", **members)
        with pytest.raises(ValueError, match=name):
            load_feature_map(tmp_path / "bad.npz")
    with np.load(path, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files if k != "state_fitted_width_"}
    np.savez(tmp_path / "bad.npz", **members)
    with pytest.raises(ValueError, match="state_fitted_width_.*is missing"):
        load_feature_map(tmp_path / "bad.npz")


# ---------------------------------------------------------------- constructor arguments
def test_drvil_refuses_a_b_min_whose_search_grid_overflows():
    data = _data()
    with pytest.raises(ValueError, match=r"b_min must be a number in \(0, 1e\+300\]"):
        DRVIL(0.2, b_min=1.79e308).fit(data)
    assert np.isfinite(DRVIL(0.2, b_min=1e300).fit(data).weights_).all()


@pytest.mark.parametrize("arg", ["phi", "rewards", "next_phi"])
def test_a_ragged_list_names_the_argument(arg):
    rng = np.random.default_rng(0)
    args = {"phi": rng.dirichlet(np.ones(2), (2, 1)), "rewards": np.zeros((2, 1)),
            "next_phi": rng.dirichlet(np.ones(2), (2, 1, 1))}
    args[arg] = [[[0.5, 0.5]], [[0.2, 0.3, 0.5]]]
    with pytest.raises(ValueError, match=f"{arg} must be a rectangular array, got a ragged "
                                         "list") as info:
        OfflineDataset.from_features(**args)
    assert "inhomogeneous" not in str(info.value)


@pytest.mark.parametrize("arg", ["phi", "next_phi"])
@pytest.mark.parametrize("bad", [None, 5])
def test_sparse_from_rows_names_a_non_sequence_argument(arg, bad):
    import scipy.sparse as sp

    rng = np.random.default_rng(0)
    args = {"phi": [sp.csr_matrix(rng.random((K, D))) for _ in range(H)],
            "rewards": rng.random((K, H)),
            "next_phi": [sp.csr_matrix(rng.random((K * A, D))) for _ in range(H)],
            "n_actions": A, arg: bad}
    with pytest.raises(TypeError, match=f"{arg} must be a list of H scipy.sparse matrices"):
        SparseOfflineDataset.from_rows(**args)


@pytest.mark.parametrize("action", [5, -1, 0.5, "left"])
@pytest.mark.parametrize("n_envs", [None, 2])
def test_an_invalid_action_in_a_gymnasium_rollout_names_the_action_and_the_space(action,
                                                                                n_envs):
    gym = pytest.importorskip("gymnasium")
    from r2pvi.evaluation import evaluate_policy

    def policy(h, obs):
        return np.full(len(obs), action, dtype=object if isinstance(action, str) else None)

    with pytest.raises(ValueError, match=rf"action {action!r} .*Discrete\(2\)"):
        evaluate_policy(gym.make("CartPole-v1"), policy, 2, seed=0, max_steps=5,
                        n_envs=n_envs)


def test_integer_valued_float_actions_still_run():
    gym = pytest.importorskip("gymnasium")
    from r2pvi.evaluation import evaluate_policy

    mean, _ = evaluate_policy(gym.make("CartPole-v1"), lambda h, o: np.ones(len(o)), 2, seed=0,
                              max_steps=5)
    assert mean == 5.0
