"""The behaviour next-state form: next_phi stored without the rows that equal phi[:, h+1].

The truth is the full form (``next_phi.npy`` whole): the rebuilt rows must be bitwise the
stored ones, and every fit bitwise the full form's, wherever the identity
``next_phi[k, h, a_{k,h+1}] = phi[k, h+1]`` breaks (episode ends, truncation, padding,
independent transitions, known values, the last step). That the rows rebuilt from the step
source are the stored ones for any range of any step is tested with the storage internals,
in test_storage_internals.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from storage_helpers import ESTIMATORS as STORAGE_ESTIMATORS
from storage_helpers import set_chunk

import r2pvi
from r2pvi import DatasetWriter, OfflineDataset
from r2pvi.envs import FiniteLinearMDP
from r2pvi.storage import ArrayField, BehaviourNext, behaviour_split

H, A = 5, 2
CENTERS = np.linspace(0.0, 1.0, 4)

ESTIMATORS = {**STORAGE_ESTIMATORS,
              "PEVI-pooled": lambda: r2pvi.PEVI(beta=0.1, time_homogeneous=True)}


def rbf_map(obs, actions):
    """A dense normalized RBF on 1-D observations, crossed with the action (d = 8)."""
    x = np.asarray(obs, dtype=float).reshape(len(actions), -1)[:, 0]
    z = np.exp(-10.0 * (x[:, None] - CENTERS) ** 2)
    z /= z.sum(axis=1, keepdims=True)
    out = np.zeros((len(actions), A, CENTERS.size))
    out[np.arange(len(actions)), np.asarray(actions)] = z
    return out.reshape(len(actions), -1)


def episodes(n=150, seed=0):
    """Episodes of 1-5 steps: terminated, truncated, or running past the horizon."""
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(n):
        T = int(rng.integers(1, H + 3))  # longer ones are cut at H
        obs = np.clip(np.cumsum(rng.normal(0, 0.2, T + 1)) + 0.5, 0, 1)[:, None]
        end = rng.random() < 0.5
        eps.append({"observations": obs, "actions": rng.integers(A, size=T),
                    "rewards": rng.random(T), "terminations": [False] * (T - 1) + [end],
                    "truncations": [False] * (T - 1) + [not end]})
    return eps


def same_bits(a, b):
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def assert_bitwise_fit(a, b):
    for name in ("weights_", "reward_weights_", "gram_inv_diag_"):
        assert same_bits(getattr(a, name), getattr(b, name)), name


def both_forms(root):
    """Trajectories from episodes, saved in both forms, written by the writer in both forms
    (uneven chunks, float32), and independent transitions in both forms: ``{case: (full,
    behaviour)}`` directories under ``root``."""
    ds = OfflineDataset.from_episodes(episodes(), rbf_map, n_actions=A, horizon=H)
    out = {"episodes": (ds.save(root / "full"),
                        ds.save(root / "beh", next_form="behaviour"))}
    K = ds.n_trajectories
    args = (ds.phi, ds.rewards, ds.next_phi, ds.next_values)
    for form in ("full", "behaviour"):
        with DatasetWriter(root / f"w-{form}", horizon=H, n_features=ds.n_features,
                           n_actions=A, next_form=form, check_simplex=False) as w:
            for s, e in ((0, 1), (1, 60), (60, 61), (61, K)):
                w.append(*(x[s:e] for x in args))
    out["writer"] = (root / "w-full", root / "w-behaviour")
    rng = np.random.default_rng(1)
    phi = rng.dirichlet(np.ones(6), (200, H))
    tr = OfflineDataset.from_features(phi, rng.random((200, H)), rng.dirichlet(
        np.ones(6), (200, H, 3)))
    out["transitions"] = (tr.save(root / "t-full"),
                          tr.save(root / "t-beh", next_form="behaviour"))
    return out


@pytest.fixture(scope="module")
def forms(tmp_path_factory):
    return both_forms(tmp_path_factory.mktemp("behaviour"))


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_every_fit_is_bitwise_the_full_forms(forms, name):
    for case in ("episodes", "writer", "transitions"):
        full, beh = (OfflineDataset.open(p) for p in forms[case])
        for ds in (full, beh):
            set_chunk(ds, 37)  # many chunks per step, side rows inside chunks
        assert_bitwise_fit(ESTIMATORS[name]().fit(beh), ESTIMATORS[name]().fit(full))


def test_behaviour_form_stores_what_it_says_and_resaves_full(forms, tmp_path):
    full, beh = forms["writer"]
    ds = OfflineDataset.open(full)
    K, d = ds.n_trajectories, ds.n_features
    n_side = json.loads((beh / "manifest.json").read_text())["next_behaviour"]["n_side"]
    data = {p: sum(np.load(f, mmap_mode="r").nbytes for f in p.glob("next_*.npy")
                   if f.name != "next_values.npy") for p in (full, beh)}
    assert data[full] == H * K * A * d * 4
    assert data[beh] == (H * K * (A - 1) + n_side) * d * 4 + H * K + (H + 1) * 8
    back = OfflineDataset.open(beh).save(tmp_path / "back")  # the default: the full form
    assert (back / "next_phi.npy").read_bytes() == (full / "next_phi.npy").read_bytes()


def test_a_third_fewer_bytes_on_trajectories_at_two_actions(tmp_path):
    rng = np.random.default_rng(4)
    K, d, H_ = 300, 6, 20
    nxt = rng.dirichlet(np.ones(d), (K, H_, A)).astype(np.float32)
    phi = np.empty((K, H_, d), np.float32)
    phi[:, 0] = rng.dirichlet(np.ones(d), K)
    phi[:, 1:] = nxt[np.arange(K)[:, None], np.arange(H_ - 1), rng.integers(A, size=(K, 19))]
    size = {}
    for form in ("full", "behaviour"):
        with DatasetWriter(tmp_path / form, horizon=H_, n_features=d, n_actions=A,
                           next_form=form) as w:
            w.append(phi, rng.random((K, H_)), nxt)
        size[form] = sum(f.stat().st_size for f in (tmp_path / form).glob("*.npy")
                         if f.name != "gram.npy")
    # phi + rewards + next: (d + 2 + 2 d) against (d + 2 + d + d / H + 1 / 4) floats
    saved = 1 - size["behaviour"] / size["full"]
    assert 0.25 < saved < 1 / 3


def test_ties_take_the_first_matching_action(tmp_path):
    rng = np.random.default_rng(2)
    K, d = 30, 4
    phi = rng.dirichlet(np.ones(d), (K, H)).astype(np.float32)
    nxt = np.repeat(phi[:, 1:, None], 3, axis=2)  # three identical rows: the next state's
    nxt = np.concatenate([nxt, rng.dirichlet(np.ones(d), (K, 1, 3)).astype(np.float32)], 1)
    ds = OfflineDataset.from_features(phi, rng.random((K, H)), nxt)
    p = ds.save(tmp_path / "b", next_form="behaviour")
    action = np.load(p / "next_action.npy")
    assert (action[:-1] == 0).all() and (action[-1] == -1).all()
    assert same_bits(OfflineDataset.open(p).next_phi, ds.next_phi)


rows_strategy = st.integers(1, 12).flatmap(lambda n: st.tuples(
    st.just(n), st.integers(1, 4), st.integers(1, 3),
    st.lists(st.integers(-2, 3), min_size=n, max_size=n), st.integers(0, 2**31)))


@settings(max_examples=60, deadline=None)
@given(rows_strategy)
def test_split_and_assemble_round_trip_bitwise(args):
    """Planted matches (also several per sample: ties), signed zeros, NaN rows, no match."""
    n, A_, d, plant, seed = args
    rng = np.random.default_rng(seed)
    rows = rng.choice(np.array([0.0, -0.0, 1.5, np.nan, 2.0**-1074]), (n, A_, d))
    following = rng.choice(np.array([0.0, 1.5, 2.0**-1074]), (n, d))
    for i, a in enumerate(plant):
        if 0 <= a < A_:
            rows[i, a] = following[i]
            if a + 1 < A_ and rng.random() < 0.5:
                rows[i, a + 1] = following[i]  # a tie: the first is taken
    action, rest, side = behaviour_split(following, rows)
    u = following.view(np.uint64)[:, None, :]
    first = [next((a for a in range(A_) if (rows[i, a].view(np.uint64) == u[i]).all()), -1)
             for i in range(n)]
    assert action.tolist() == first
    last, rest1, side1 = behaviour_split(None, rows)  # the last step: every row in the table
    assert (last == -1).all() and side1.shape == (n, d)
    nxt = BehaviourNext(ArrayField(np.stack([action, last])), ArrayField(np.stack([rest, rest1])),
                        ArrayField(np.stack([np.zeros_like(following), following])),
                        np.concatenate([side, side1]), [0, len(side), len(side) + n])
    for h in (0, 1):
        assert nxt.features(h).tobytes() == rows.tobytes()
        s = n // 3
        assert nxt.features(h, s, n).tobytes() == rows[s:].tobytes()


def corrupt(src, tmp_path, edit):
    import shutil

    dst = tmp_path / "c"
    shutil.copytree(src, dst)
    edit(dst)
    return dst


def _manifest_edit(fn):
    def edit(p):
        mf = json.loads((p / "manifest.json").read_text())
        fn(mf)
        (p / "manifest.json").write_text(json.dumps(mf))
    return edit


@pytest.mark.parametrize("edit, match", [
    (_manifest_edit(lambda m: m["files"].pop("next_rest")), "next_rest"),
    (lambda p: (p / "next_side.npy").unlink(), "next_side"),
    (_manifest_edit(lambda m: m.pop("next_behaviour")), "next_behaviour"),
    (_manifest_edit(lambda m: m["next_behaviour"].update(version=99)), "upgrade r2pvi"),
    (_manifest_edit(lambda m: m["next_behaviour"].update(n_side=1)), "next_side_offsets"),
    (lambda p: np.save(p / "next_side_offsets.npy", np.zeros(H + 1, np.int64)),
     "next_side_offsets"),
    (lambda p: np.save(p / "next_rest.npy", np.zeros((3, 3))), "next_rest"),
])
def test_tampered_or_missing_fields_name_the_field(forms, tmp_path, edit, match):
    p = corrupt(forms["writer"][1], tmp_path, edit)
    with pytest.raises(ValueError, match=match):
        OfflineDataset.open(p)


def test_corrupt_behaviour_actions_are_caught_when_read(forms, tmp_path):
    def flip(p):  # a matched sample marked as a side-table row: the counts disagree
        a = np.load(p / "next_action.npy")
        a[0, np.flatnonzero(a[0] >= 0)[0]] = -1
        np.save(p / "next_action.npy", a)

    ds = OfflineDataset.open(corrupt(forms["writer"][1], tmp_path, flip))
    with pytest.raises(ValueError, match="next_action of step 0"):
        ESTIMATORS["TV"]().fit(ds)


def test_next_form_is_checked(forms, tmp_path):
    ds = OfflineDataset.open(forms["episodes"][0])
    with pytest.raises(ValueError, match="next_form"):
        ds.save(tmp_path / "x", next_form="behavior")
    with pytest.raises(ValueError, match="next_form"):
        DatasetWriter(tmp_path / "y", horizon=H, n_features=8, n_actions=A, next_form="diff")
    with pytest.raises(ValueError, match="directory"):
        ds.save(tmp_path / "x.npz", next_form="behaviour")
    rng = np.random.default_rng(3)
    S, d = 4, 3
    env = FiniteLinearMDP(rng.dirichlet(np.ones(d), (3, S, A)), rng.random((3, d)),
                          rng.dirichlet(np.ones(S), (3, d)), initial=1)
    with pytest.raises(ValueError, match="next_form='full'"):  # indices: no features stored
        env.collect(20, seed=0).save(tmp_path / "t", next_form="behaviour")


def test_table_datasets_keep_private_extras_and_validate_without_simplex_checks():
    """Dataset construction copies no more than it must, and drops no check."""
    rng = np.random.default_rng(5)
    K, S, d = 40, 6, 3
    table = rng.dirichlet(np.ones(d), (S, A))
    s, a = rng.integers(S, size=(K, H)), rng.integers(A, size=(K, H))
    ns_sm = rng.integers(S, size=(H, K))  # step-major already: a view needs no transpose
    ds = OfflineDataset.from_next_state_table(table[s, a], rng.random((K, H)), ns_sm.T, table,
                                              check_simplex=False, states=s, actions=a)
    for mine, theirs in ((ds.next_states, ns_sm), (ds.states, s), (ds.actions, a)):
        assert not np.shares_memory(mine, theirs) and not mine.flags.writeable
    np.testing.assert_array_equal(ds.next_states, ns_sm.T)
    phi = table[s, a]
    phi[3, 1, 0] = np.nan
    with pytest.raises(ValueError, match="phi contains 1 NaN"):
        OfflineDataset.from_next_state_table(phi, np.zeros((K, H)), ns_sm.T, table,
                                             check_simplex=False)
    with pytest.raises(ValueError, match="next_states must lie"):
        OfflineDataset.from_next_state_table(table[s, a], np.zeros((K, H)), ns_sm.T + S, table)
    with pytest.raises(ValueError, match=r"actions must lie in \[0, 2\)"):
        OfflineDataset.from_next_state_table(table[s, a], np.zeros((K, H)), ns_sm.T, table,
                                             actions=a + 1)


def test_save_matches_after_the_cast_to_float32(forms, tmp_path):
    """float64 trajectories saved as float32: rows are compared after the cast, as stored."""
    ds = OfflineDataset.open(forms["episodes"][0])
    assert ds.dtype == np.float64
    full = OfflineDataset.open(ds.save(tmp_path / "f", dtype="float32"))
    beh = OfflineDataset.open(ds.save(tmp_path / "b", dtype="float32", next_form="behaviour"))
    assert beh.dtype == np.float32 and same_bits(beh.next_phi, full.next_phi)
    n_side = json.loads((tmp_path / "b" / "manifest.json").read_text())["next_behaviour"]
    assert n_side["n_side"] < 0.5 * H * ds.n_trajectories
    assert_bitwise_fit(ESTIMATORS["KL"]().fit(beh), ESTIMATORS["KL"]().fit(full))
