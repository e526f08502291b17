"""Internals of the storage: what a dataset's step source records and where ``fit`` takes its
numbers from.

These tests reach into private state (``OfflineDataset._source``, the step source;
``OfflineDataset._step_product``, its read of ``phi_h @ z``; ``DatasetWriter._flags``)
because no public API exposes it. They check how the numbers are found, not what a user
sees; when the internals change, change these tests with them. The behaviours a user sees
are tested through the public API in the files named for them (see docs/contributing.md).
"""

import json

import numpy as np
import pytest
from helpers import A, D, H, linear_data
from test_next_form_behaviour import H as BEH_H
from test_next_form_behaviour import both_forms, same_bits

from r2pvi import PEVI, DatasetWriter, OfflineDataset
from r2pvi.data.storage import behaviour
from r2pvi.storage import BehaviourNext


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
