"""Storage findings of the adversarial review (2026-12-02): float32 overflow refused before
anything is written, errors that say which append and step, empty appends, a rejected chunk
that leaves the writer's flags alone, manifests with a damaged format version."""

from __future__ import annotations

import json

import numpy as np
import pytest

from r2pvi import DatasetWriter, OfflineDataset


def arrays(k, H=3, d=4, A=2, seed=0):
    rng = np.random.default_rng(seed)
    phi = rng.dirichlet(np.ones(d), size=(k, H))
    next_phi = rng.dirichlet(np.ones(d), size=(k, H, A))
    return phi, rng.uniform(0.0, 1.0, (k, H)), next_phi


def test_float32_save_refuses_finite_values_beyond_its_range(tmp_path):
    """They became inf with only a RuntimeWarning, gram.npy was non-finite and fits NaN."""
    phi, rewards, next_phi = arrays(10)
    phi[3, 1, 2] = 1e39
    ds = OfflineDataset.from_features(phi, rewards, next_phi, check_simplex=False)
    with pytest.raises(ValueError, match="beyond float32's range.*dtype='float64'"):
        ds.save(tmp_path / "d", dtype="float32")
    assert not any(tmp_path.iterdir())  # nothing left behind
    ds.save(tmp_path / "d64", dtype="float64")  # float64 keeps them
    with pytest.raises(ValueError, match="beyond float32's range"):
        OfflineDataset.from_features(phi, rewards, next_phi, check_simplex=False,
                                     dtype="float32")
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2,
                       check_simplex=False) as w:
        with pytest.raises(ValueError, match="phi holds finite values beyond float32"):
            w.append(phi, rewards, next_phi)
        w.append(*arrays(5))
    assert OfflineDataset.open(tmp_path / "w").n_trajectories == 5


def test_a_bad_append_names_the_append_and_step_and_leaves_the_writer_as_it_was(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        w.append(*arrays(4))
        flags = list(w._flags)
        phi, rewards, next_phi = arrays(6, seed=1)
        phi[2, 1] = -phi[2, 1]  # negative features at step 0 would flip a flag
        phi[5, 2, 0] = np.nan  # and the chunk fails at step 2
        with pytest.raises(ValueError, match=r"append #1 \(trajectories 4\.\.9.*step h = 2"):
            w.append(phi, rewards, next_phi)
        assert w._flags == flags
        w.append(*arrays(0))  # an empty batch (a stream's tail): nothing, no error
        w.append(*arrays(2, seed=2))
    ds = OfflineDataset.open(tmp_path / "w")
    assert ds.n_trajectories == 6
    assert ds._source.nonnegative_phi


def test_empty_append_with_mismatched_fields_is_refused(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        phi, rewards, next_phi = arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but rewards"):
            w.append(phi[:0], rewards, next_phi[:0])
        w.append(phi, rewards, next_phi)


@pytest.mark.parametrize("bad", [0, 1, -3, 2.0, "2", True, None])
def test_damaged_format_versions_are_refused_with_the_right_advice(tmp_path, bad):
    """Versions 0, -3, 1 opened; 2.0, "2", None said "upgrade r2pvi" (wrong advice)."""
    path = OfflineDataset.from_features(*arrays(3)).save(tmp_path / "d")
    mf = json.loads((path / "manifest.json").read_text())
    (path / "manifest.json").write_text(json.dumps({**mf, "format_version": bad}))
    with pytest.raises(ValueError, match="must be an integer >= 2") as err:
        OfflineDataset.open(path)
    assert "upgrade" not in str(err.value)


def test_writer_records_reward_noise_and_empty_appends_check_next_values(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2,
                       reward_noise=0.1) as w:
        phi, rewards, next_phi = arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but next_values"):
            w.append(phi[:0], rewards[:0], next_phi[:0], next_values=np.zeros((7, 1)))
        w.append(phi, rewards, next_phi)
    assert OfflineDataset.open(tmp_path / "w").reward_noise == 0.1
