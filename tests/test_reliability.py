"""Reliable files and inputs: atomic saves, validated loads, named errors for bad inputs."""

import json
import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import DRPVI, PEVI, R2PVI, OfflineDataset, cressie_read, load
from r2pvi.duals import BUILTIN_DIVERGENCES, GramMatrixError
from r2pvi.envs import SimulatedLinearMDP
from r2pvi.evaluation import expected_return, monte_carlo_return

SRC = str(Path(r2pvi.__file__).resolve().parents[1])
META = "__r2pvi_meta__"


def make_data(K=40, H=3, d=4, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(K, H))
    next_phi = rng.dirichlet(np.ones(d), size=(K, H, A))
    theta = rng.uniform(size=(H, d))
    return OfflineDataset.from_features(phi, np.einsum("khd,hd->kh", phi, theta), next_phi)


@pytest.fixture(scope="module")
def data():
    return make_data()


@pytest.fixture
def model_file(tmp_path, data):
    return R2PVI("kl", 0.5, beta=0.1).fit(data).save(tmp_path / "model.npz")


def rewrite(path, out, *, header=None, drop=(), **arrays):
    """Copy an r2pvi file with some arrays replaced/dropped and the header edited (no pickle)."""
    with np.load(path, allow_pickle=False) as npz:
        content = {k: npz[k] for k in npz.files if k not in drop}
    meta = json.loads(str(content[META]))
    if header is not None:
        header(meta)
    content[META] = np.array(meta if isinstance(meta, str) else json.dumps(meta))
    content.update(arrays)
    np.savez(out, **content)
    return out


# --------------------------------------------------------------------------- atomic saves
def test_a_save_failing_part_way_keeps_the_previous_file(tmp_path, data, monkeypatch):
    est = R2PVI("tv", 0.5, beta=0.1).fit(data)
    path = est.save(tmp_path / "m.npz")
    good = path.read_bytes()

    def half_written(fh, **arrays):
        fh.write(b"PK\x03\x04" + b"\0" * 4000)  # a partial archive, then the disk fills up
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", half_written)
    with pytest.raises(OSError, match="No space"):
        R2PVI("kl", 0.5).fit(data).save(path)
    assert path.read_bytes() == good
    assert os.listdir(tmp_path) == ["m.npz"]  # no temporary file left behind
    np.testing.assert_array_equal(load(path).weights_, est.weights_)


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX")
def test_a_save_over_the_file_size_limit_keeps_the_previous_file(tmp_path):
    # `ulimit -f 8` (8 KiB) while saving over a good file.
    path = tmp_path / "ds.npz"
    small = make_data(K=2)
    small.save(path)
    good = path.read_bytes()
    assert len(good) < 8192
    script = textwrap.dedent(f"""
        import resource, sys
        import numpy as np
        from r2pvi import OfflineDataset
        rng = np.random.default_rng(1)
        big = OfflineDataset.from_features(rng.random((400, 5, 6)), rng.random((400, 5)),
                                           rng.random((400, 5, 2, 6)), check_simplex=False)
        resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))
        try:
            big.save({str(path)!r})
        except OSError as exc:
            print("save failed:", exc.errno)
            sys.exit(0)
        sys.exit(3)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": SRC}, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "save failed" in res.stdout
    assert path.read_bytes() == good
    assert sorted(os.listdir(tmp_path)) == ["ds.npz"]
    assert OfflineDataset.load(path).n_trajectories == 2


def test_save_keeps_permissions_like_a_plain_write(tmp_path, data):
    path = PEVI().fit(data).save(tmp_path / "p.npz")
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


# --------------------------------------------------------------------------- validated loads
def _bad_model_files(tmp_path, good):
    raw = good.read_bytes()
    (tmp_path / "empty.npz").write_bytes(b"")
    (tmp_path / "dir.npz").mkdir()
    (tmp_path / "random.npz").write_bytes(np.random.default_rng(0).bytes(3000))
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    cases = {
        "empty.npz": "empty",
        "dir.npz": "directory",
        "random.npz": "not a zip",
        "trunc.npz": "damaged or truncated",
    }

    def rw(name, match, **kw):
        rewrite(good, tmp_path / name, **kw)
        cases[name] = match

    rw("notjson.npz", "'header' is not valid JSON", **{META: np.array("{not json")})
    rw("list.npz", "'header' must be a JSON object", **{META: np.array("[1, 2]")})
    for i, bad in enumerate([True, 0, "1", 1.5, None]):
        rw(f"version{i}.npz", "'format_version' must be an integer >= 1",
           header=lambda m, b=bad: m.update(format_version=b))
    rw("nokey.npz", "'weights_' is missing", drop=("weights_",))
    rw("noparams.npz", "'params'", header=lambda m: m.pop("params"))
    weights = load(good).weights_
    rw("nan.npz", "'weights_' has 1 NaN", weights_=_with_nan(weights))
    rw("strings.npz", "'weights_' must be numeric", weights_=weights.astype(str))
    rw("invdiag.npz", "'gram_inv_diag_' must be > 0",
       gram_inv_diag_=-load(good).gram_inv_diag_)
    rw("shape.npz", "'reward_weights_' must have shape", reward_weights_=np.ones((2, 2)))
    # A version-1 file must carry its (H, d, d) Cholesky factors (version 2 does not).
    rw("v1.npz", "'gram_cholesky_' is missing", header=lambda m: m.update(format_version=1))
    rw("lam.npz", "'params' fail the estimator's checks: lam must be > 0",
       header=lambda m: m["params"].update(lam=-0.5))
    rw("div.npz", "'params.divergence' is not a divergence",
       header=lambda m: m["params"].update(divergence={"__divergence__": {"name": "nope"}}))
    rw("unknownparam.npz", "unknown parameters", header=lambda m: m["params"].update(lamm=1))
    rw("class.npz", "'estimator' is 'Evil'", header=lambda m: m.update(estimator="Evil"))
    rw("fit.npz", "'fit_params.beta'", header=lambda m: m["fit_params"].update(beta=7.0))
    rw("penalty.npz", "'fit_params'", header=lambda m: m["fit_params"].update(penalty="x"))
    rw("nact.npz", "'n_actions' must be an integer >= 1",
       header=lambda m: m.update(n_actions=True))
    rw("kind.npz", "'kind' is 'OfflineDataset'", header=lambda m: m.update(kind="OfflineDataset"))
    return cases


def _with_nan(w):
    w = w.copy()
    w[0, 0] = np.nan
    return w


def test_every_bad_model_file_is_a_value_error_naming_file_and_field(tmp_path, model_file):
    cases = _bad_model_files(tmp_path, model_file)
    assert load(model_file).n_actions_ == 2  # the good file loads
    for name, match in cases.items():
        with pytest.raises(ValueError) as info:
            load(tmp_path / name)
        message = str(info.value)
        assert str(tmp_path / name) in message, (name, message)
        assert match in message, (name, message)
    with pytest.raises(FileNotFoundError, match="no such file"):
        load(tmp_path / "absent.npz")


def test_bad_dataset_files_are_value_errors_naming_file_and_field(tmp_path, data):
    good = data.save(tmp_path / "ds.npz")
    phi = data.phi.copy()
    phi[0, 0, 0] = np.nan
    cases = {
        "nophi.npz": ({"drop": ("phi",)}, "'phi' is missing"),
        "strings.npz": ({"rewards": data.rewards.astype(str)}, "rewards must be a numeric"),
        "nan.npz": ({"phi": phi}, "phi contains 1 NaN"),
        "shape.npz": ({"rewards": np.ones((3, 3))}, "rewards must have shape"),
        "extra.npz": ({"evil": np.ones(2)}, "'evil' is not a field"),
        "actions.npz": ({"extra_actions": np.full((40, 3), 0.7)}, "actions must be integer"),
    }
    for name, (kw, match) in cases.items():
        rewrite(good, tmp_path / name, **kw)
        with pytest.raises(ValueError, match=match) as info:
            OfflineDataset.load(tmp_path / name)
        assert str(tmp_path / name) in str(info.value)
    (tmp_path / "half.npz").write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match="half.npz is damaged or truncated"):
        OfflineDataset.load(tmp_path / "half.npz")


# --------------------------------------------------------------------------- inputs
def test_actions_must_be_integer_indices_and_states_are_private_read_only_copies():
    rng = np.random.default_rng(0)
    K, H, d, A = 5, 2, 3, 2
    phi, r = rng.dirichlet(np.ones(d), (K, H)), rng.random((K, H))
    nphi = rng.dirichlet(np.ones(d), (K, H, A))
    with pytest.raises(TypeError, match="actions must be integer indices, got non-integer"):
        OfflineDataset.from_features(phi, r, nphi, actions=np.full((K, H), 0.7))
    with pytest.raises(TypeError, match="actions must be integer indices, got dtype <U1"):
        OfflineDataset.from_features(phi, r, nphi, actions=np.full((K, H), "a"))
    with pytest.raises(ValueError, match=r"actions must lie in \[0, 2\)"):
        OfflineDataset.from_features(phi, r, nphi, actions=np.full((K, H), 2))
    with pytest.raises(TypeError, match="actions must be integer"):
        OfflineDataset.from_transitions(np.zeros((K, H), int), [["a"] * H] * K, r,
                                        np.zeros((K, H), int), lambda s, a: phi[0, 0][None]
                                        .repeat(len(s), 0), A)
    states = np.arange(K * H).reshape(K, H)
    ds = OfflineDataset.from_features(phi, r, nphi, states=states, actions=np.ones((K, H)),
                                      next_states=states + 1)
    assert ds.actions.dtype == np.int64 and (ds.actions == 1).all()
    states[0, 0] = 99  # the caller's array stays the caller's
    assert ds.states[0, 0] == 0
    for arr in (ds.states, ds.actions, ds.next_states, ds.subset([1, 0]).states):
        with pytest.raises(ValueError, match="read-only"):
            arr[0, 0] = 7


def test_subset_indices_are_checked(data):
    K = data.n_trajectories
    with pytest.raises(ValueError, match=rf"indices must lie in \[0, {K}\)"):
        data.subset([K + 5])
    with pytest.raises(ValueError, match="indices must lie"):
        data.subset([-1])
    with pytest.raises(TypeError, match="indices must be integer indices"):
        data.subset([0.5])
    with pytest.raises(TypeError, match="indices must be integer indices"):
        data.subset(["0"])
    with pytest.raises(ValueError, match="one entry per trajectory"):
        data.subset(np.ones(K + 1, bool))
    assert data.subset([2.0, 3]).n_trajectories == 2


def test_evaluation_requires_a_policy_and_two_episodes():
    env = SimulatedLinearMDP()
    with pytest.raises(TypeError, match="expected_return needs a policy"):
        expected_return(env, None)
    with pytest.raises(TypeError, match="needs a policy"):
        monte_carlo_return(env, None, 10, seed=0)
    with pytest.raises(ValueError, match="n_episodes must be >= 2"):
        monte_carlo_return(env, "uniform", 1, seed=0)
    mean, se = monte_carlo_return(env, "uniform", 2, seed=0)
    assert np.isfinite(mean) and np.isfinite(se)


def test_negative_seeds_are_named_errors():
    with pytest.raises(ValueError, match="seed must be >= 0"):
        SimulatedLinearMDP().collect(5, seed=-1)
    with pytest.raises(ValueError, match="seed must be >= 0"):
        monte_carlo_return(SimulatedLinearMDP(), "uniform", 5, seed=-3)


def test_numpy_scalars_are_accepted_everywhere_including_save(tmp_path, data):
    est = R2PVI("tv", np.float64(0.5), beta=np.float32(0.25), gamma=np.int64(1),
                variance_aware=np.True_, v_min=np.float64(0.0), r_max=np.float64(1.0)).fit(data)
    ref = R2PVI("tv", 0.5, beta=0.25, gamma=1, variance_aware=True, v_min=0.0).fit(data)
    np.testing.assert_allclose(est.weights_, ref.weights_, rtol=1e-12)
    back = load(est.save(tmp_path / "np.npz"))
    assert back.get_params()["variance_aware"] is True
    np.testing.assert_array_equal(back.weights_, est.weights_)
    drp = DRPVI(np.float64(0.1), variance_aware=np.False_, penalty=np.str_("l2")).fit(data)
    assert load(drp.save(tmp_path / "d.npz")).get_params()["penalty"] == "l2"


def test_collinear_features_with_tiny_gamma_name_the_step_and_gamma():
    K, H = 30, 3
    a = np.random.default_rng(0).dirichlet(np.ones(2), size=(K, H))
    phi = np.concatenate([a, 0.5 * a[..., :1]], axis=-1)  # feature 2 = feature 0 / 2
    gram = phi[:, 2].T @ phi[:, 2] + 1e-300 * np.eye(3)
    with pytest.raises(np.linalg.LinAlgError):  # the failure is real at the last step
        np.linalg.cholesky(gram)
    nphi = np.broadcast_to(phi[:, :, None], (K, H, 2, 3))
    ds = OfflineDataset.from_features(phi, np.ones((K, H)), nphi, check_simplex=False)
    with pytest.raises(GramMatrixError, match=r"step h = 2 \(0-based\).*gamma = 1e-300 is too "
                                              "small") as info:
        R2PVI("kl", 1.0, gamma=1e-300).fit(ds)
    assert isinstance(info.value, ValueError) and isinstance(info.value, np.linalg.LinAlgError)
    assert np.isfinite(R2PVI("kl", 1.0, gamma=1e-3).fit(ds).weights_).all()


def test_every_builtin_divergence_and_fitted_estimator_pickles(data):
    for div in [*BUILTIN_DIVERGENCES.values(), cressie_read(3), cressie_read(0.5)]:
        back = pickle.loads(pickle.dumps(div))
        assert back == div and back.name == div.name
        t = np.array([0.3, 1.0, 2.5])
        np.testing.assert_array_equal(back.f(t), div.f(t))
        np.testing.assert_array_equal(back.conjugate(t - 1), div.conjugate(t - 1))
    est = R2PVI(cressie_read(3), 0.5, beta=0.1).fit(data)
    back = pickle.loads(pickle.dumps(est))
    phi_all = data.next_phi[:5, 0]
    np.testing.assert_array_equal(back.q_values(phi_all, 1), est.q_values(phi_all, 1))


@pytest.fixture(scope="module")
def good_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("good")
    return R2PVI("kl", 0.5, beta=0.1).fit(make_data(K=20, d=3)).save(folder / "good.npz")


@settings(max_examples=int(os.environ.get("R2PVI_DAMAGE_EXAMPLES", 60)), deadline=None)
@given(st.data())
def test_a_damaged_file_loads_identically_or_raises_a_named_value_error(
    tmp_path_factory, good_model, data
):
    # Property: whatever bytes are flipped or cut, load gives back the same model or a
    # ValueError naming the file, never another exception or a silently different model.
    tmp = tmp_path_factory.mktemp("damaged")
    good = good_model.read_bytes()
    raw = bytearray(good)
    if data.draw(st.booleans(), label="truncate"):
        raw = raw[: data.draw(st.integers(0, len(raw) - 1), label="cut")]
    else:
        for _ in range(data.draw(st.integers(1, 4), label="flips")):
            i = data.draw(st.integers(0, len(raw) - 1), label="offset")
            raw[i] ^= data.draw(st.integers(1, 255), label="xor")
    path = tmp / "m.npz"
    path.write_bytes(bytes(raw))
    try:
        est = load(path)
    except ValueError as exc:
        assert str(path) in str(exc)
    else:
        ref = load(good_model)
        for name in ("weights_", "reward_weights_", "gram_inv_diag_"):
            np.testing.assert_array_equal(getattr(est, name), getattr(ref, name))
        assert est.get_params()["lam"] == ref.get_params()["lam"]


# --------------------------------------------------------------------------- BLAS threads
def _blas_threads_seen_by_fit(monkeypatch, data):
    from threadpoolctl import threadpool_info

    from r2pvi.algorithms import pevi

    seen = []
    original = pevi.RidgeRule.__call__

    def spy(self, E, v, ctx):
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
        return original(self, E, v, ctx)

    monkeypatch.setattr(pevi.RidgeRule, "__call__", spy)
    PEVI().fit(data)
    return set(seen)


def test_a_fit_uses_one_blas_thread_unless_told_otherwise(monkeypatch, data):
    from threadpoolctl import threadpool_limits

    from r2pvi.experiments.runner import Task, run_tasks

    with threadpool_limits(2, user_api="blas"):  # the caller's setting (2 cores here or not)
        monkeypatch.delenv("R2PVI_BLAS_THREADS", raising=False)
        assert _blas_threads_seen_by_fit(monkeypatch, data) == {1}
        monkeypatch.setenv("R2PVI_BLAS_THREADS", "0")  # leave BLAS alone
        assert _blas_threads_seen_by_fit(monkeypatch, data) == {2}
        monkeypatch.setenv("R2PVI_BLAS_THREADS", "3")
        assert _blas_threads_seen_by_fit(monkeypatch, data) == {3}
        monkeypatch.setenv("R2PVI_BLAS_THREADS", "many")
        with pytest.raises(ValueError, match="R2PVI_BLAS_THREADS must be an integer >= 0"):
            PEVI().fit(data)
        monkeypatch.delenv("R2PVI_BLAS_THREADS")

        def task(seq):
            from threadpoolctl import threadpool_info

            return [{"t": i["num_threads"]} for i in threadpool_info()
                    if i["user_api"] == "blas"]

        assert {r["t"] for r in run_tasks([Task(task)] * 2)} == {1}
        assert {r["t"] for r in run_tasks([Task(task)], blas_threads=0)} == {2}
    with pytest.raises(ValueError, match="jobs must be an integer >= 1, or -1"):
        run_tasks([Task(task)], jobs=0)
