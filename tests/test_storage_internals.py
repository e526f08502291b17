"""Internals of the storage: what a dataset's step source records and where ``fit`` takes its
numbers from.

These tests reach into private state (``OfflineDataset._source``, the step source;
``OfflineDataset._step_product``, its read of ``phi_h @ z``; ``DatasetWriter._flags``)
because no public API exposes it. They check how the numbers are found, not what a user
sees; when the internals change, change these tests with them. The behaviours a user sees
are tested through the public API in the files named for them (see docs/contributing.md).
"""

import json
import warnings

import numpy as np
import pytest
from helpers import A, D, H, linear_data
from storage_helpers import small_arrays
from test_next_form_behaviour import H as BEH_H
from test_next_form_behaviour import both_forms, same_bits

from r2pvi import PEVI, DatasetWriter, OfflineDataset
from r2pvi.data.storage import behaviour
from r2pvi.storage import BehaviourNext


# ---------------------------------------------------------------- the reward check
def test_reward_weights_are_checked_through_the_rewards_they_give(monkeypatch):
    data, phi, r, nxt, theta = linear_data()
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
    data, phi, r, nxt, _ = linear_data(scale=5.0)
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
    del manifest["reward_range"]  # a manifest without the record: the rewards are read once
    (path / "manifest.json").write_text(json.dumps(manifest))
    assert OfflineDataset.open(path).reward_range == expect
    assert data.subset(np.arange(5)).reward_range == (float(r[:5].min()), float(r[:5].max()))


def _float32_simplex(seed, K=4000, H=4, d=6, A=2):
    rng = np.random.default_rng(seed)
    phi = rng.random((K, H, d), dtype=np.float32)
    phi /= phi.sum(-1, keepdims=True)  # sums 1 within ~1e-7 in float64: not unit rows
    nphi = rng.random((K, H, A, d), dtype=np.float32)
    nphi /= nphi.sum(-1, keepdims=True)
    return phi, nphi


def test_directories_record_row_sums_and_the_reward_check_reads_no_features(tmp_path):
    """float32 simplex rows (sums 1 within ~1e-7, not unit rows): both writers record the
    range of the stored rows' sums (``phi_row_sums``), and ``fit``'s reward check with
    ``reward_weights`` settles every step from it, reading no feature. The bound is
    rigorous: rewards above ``r_max`` are still refused, and a manifest without the record
    still reads the rows."""
    from r2pvi import R2PVI
    from r2pvi.algorithms import base

    phi, nphi = _float32_simplex(0)
    H, d = phi.shape[1], phi.shape[2]
    theta = np.random.default_rng(1).uniform(0.0, 0.99, (H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    with DatasetWriter(tmp_path / "w", horizon=H, n_features=d, n_actions=2) as w:
        w.append(phi, rewards, nphi)
    OfflineDataset.from_features(phi.astype(float), rewards, nphi.astype(float),
                                 check_simplex=False).save(tmp_path / "s", dtype="float32")
    for name in ("w", "s"):
        mf = json.loads((tmp_path / name / "manifest.json").read_text())
        lo, hi = mf["phi_row_sums"]
        sums = phi.astype(np.float64).sum(-1)
        assert lo == pytest.approx(sums.min(), abs=1e-15) and lo < 1.0 - 1e-9
        assert hi == pytest.approx(sums.max(), abs=1e-15) and hi > 1.0 + 1e-9
        ds = OfflineDataset.open(tmp_path / name)
        reads = []
        original = type(ds)._step_product

        def spy(self, h, t, original=original, reads=reads):
            reads.append(h)
            return original(self, h, t)

        with pytest.MonkeyPatch.context() as m:
            m.setattr(type(ds), "_step_product", spy)
            R2PVI("tv", 1.0, reward_weights=theta, r_max=1.0).fit(ds)
            assert reads == []
            too_big = theta.copy()
            too_big[2, 0] = 1.5  # rewards up to ~1.5 on the rows that weigh feature 0
            with pytest.raises(ValueError, match="r_max"):
                base.check_reward_range(ds, 1.0, too_big)
    # a manifest without the record: the rows are read, the answer is the same
    mf = json.loads((tmp_path / "w" / "manifest.json").read_text())
    del mf["phi_row_sums"]
    (tmp_path / "w" / "manifest.json").write_text(json.dumps(mf))
    ds = OfflineDataset.open(tmp_path / "w")
    assert ds._source.phi_row_sums is None
    reads = []
    original = type(ds)._step_product
    with pytest.MonkeyPatch.context() as m:
        m.setattr(type(ds), "_step_product",
                  lambda self, h, t: (reads.append(h), original(self, h, t))[1])
        base.check_reward_range(ds, 1.0, theta)
    assert reads == list(range(H))


def test_validated_arrays_know_their_row_sums_and_the_reward_check_reads_no_features():
    """In memory too: validation records phi's row-sum range (float32-rounded simplex rows,
    not unit rows), so ``reward_weights`` are checked without a product per step; without the
    simplex check (no row sums) every step is read."""
    from r2pvi.algorithms import base

    phi, nphi = _float32_simplex(2)
    H, d = phi.shape[1], phi.shape[2]
    theta = np.random.default_rng(3).uniform(0.0, 0.99, (H, d))
    rewards = np.einsum("khd,hd->kh", phi, theta)
    for check, expected in ((True, []), (False, list(range(H)))):
        ds = OfflineDataset.from_features(phi.astype(float), rewards, nphi.astype(float),
                                          check_simplex=check)
        assert (ds._source.phi_row_sums is not None) == check
        assert not ds._source.unit_rows
        reads = []
        original = type(ds)._step_product
        with pytest.MonkeyPatch.context() as m:
            m.setattr(type(ds), "_step_product",
                      lambda self, h, t, reads=reads, original=original:
                      (reads.append(h), original(self, h, t))[1])
            base.check_reward_range(ds, 1.0, theta)
        assert reads == expected


# ---------------------------------------------------------------- what was checked when built
def test_in_memory_datasets_are_checked_once_when_built():
    """The constructors' errors are unchanged, and what they checked is not checked again."""
    K = 24
    rng = np.random.default_rng(0)
    phi = rng.dirichlet(np.ones(D), (K, H))
    nphi = rng.dirichlet(np.ones(D), (K, H, A))
    rewards = rng.uniform(0.05, 0.95, (K, H))
    bad = phi.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="phi contains 1 NaN"):
        OfflineDataset.from_features(bad, rewards, nphi)
    ds = OfflineDataset.from_features(phi, rewards, nphi)
    assert ds._source.checked == {"phi", "rewards", "next"}
    assert ds.subset(np.arange(3))._source.checked == {"phi", "rewards", "next"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = OfflineDataset.from_observations(
            np.zeros((K, H, 1)), np.zeros((K, H), int), rewards, np.zeros((K, H, 1)),
            lambda x, a: np.ones((len(x), 2)), A)
    assert obs._source.checked == {"rewards"}  # the features are computed while fitting


# ---------------------------------------------------------------- the writer
def test_a_bad_append_names_the_append_and_step_and_leaves_the_writer_as_it_was(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        w.append(*small_arrays(4))
        flags = list(w._flags)
        phi, rewards, next_phi = small_arrays(6, seed=1)
        phi[2, 1] = -phi[2, 1]  # negative features at step 0 would flip a flag
        phi[5, 2, 0] = np.nan  # and the chunk fails at step 2
        with pytest.raises(ValueError, match=r"append #1 \(trajectories 4\.\.9.*step h = 2"):
            w.append(phi, rewards, next_phi)
        assert w._flags == flags
        w.append(*small_arrays(0))  # an empty batch (a stream's tail): nothing, no error
        w.append(*small_arrays(2, seed=2))
    ds = OfflineDataset.open(tmp_path / "w")
    assert ds.n_trajectories == 6
    assert json.loads((tmp_path / "w" / "manifest.json").read_text())["nonnegative_phi"] is True


# ---------------------------------------------------------------- the behaviour next-state form
@pytest.fixture(scope="module")
def forms(tmp_path_factory):
    return both_forms(tmp_path_factory.mktemp("behaviour"))


@pytest.mark.parametrize("case", ["episodes", "writer", "transitions"])
def test_rebuilt_next_features_are_the_stored_ones_bitwise(forms, case, monkeypatch):
    # side positions: counts per 7 samples (patched where BehaviourNext reads it)
    monkeypatch.setattr(behaviour, "SIDE_BLOCK", 7)
    full, beh = (OfflineDataset.open(p) for p in forms[case])
    assert isinstance(beh._source.next, BehaviourNext)
    _, blocks = beh._source.next._index(0)[1]
    assert len(blocks) == full.n_trajectories // 7 + 2  # the patch took effect
    assert same_bits(beh.next_phi, full.next_phi)
    assert same_bits(beh.next_values, full.next_values)
    for h, s, e in ((0, 3, 50), (BEH_H - 1, 0, 7), (2, 100, 101)):  # any range, any step
        assert same_bits(beh._source.next.features(h, s, e),
                         full._source.next.features(h, s, e))
    assert same_bits(beh.subset([7, 0, 3]).next_phi, full.subset([7, 0, 3]).next_phi)
    mf = json.loads((forms[case][1] / "manifest.json").read_text())
    K = full.n_trajectories
    n_side = mf["next_behaviour"]["n_side"]
    assert mf["next"] == "behaviour" and "next_phi" not in mf["files"]
    if case == "transitions":  # independent next states: nothing matches, all in the table
        assert n_side == BEH_H * K
    else:  # the last step always, plus episode ends and padding; the rest rebuilt from phi
        ends = (full.phi[:, 1:].sum(axis=2) == 0).sum()  # steps h with no step h+1 data
        assert K <= n_side <= K + ends
        assert n_side < 0.5 * BEH_H * K
