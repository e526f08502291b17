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

from r2pvi import PEVI, DatasetWriter, OfflineDataset


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
