"""``DatasetWriter``: a dataset directory written chunk by chunk.

Each appended chunk is validated (shapes, types, finite numbers) and a rejected one changes
nothing; nothing appears at the path before ``close`` (an error inside ``with``, or a dropped
writer, leaves nothing behind); known next-state values may come in some chunks only; the
simplex warning is given once. What the writer records in the manifest is read back by
``OfflineDataset.open``.
"""

from __future__ import annotations

import numpy as np
import pytest
from storage_helpers import A, D, H, make_arrays, small_arrays

import r2pvi
from r2pvi import DatasetWriter, OfflineDataset


def test_writer_validates_each_chunk_and_is_atomic(tmp_path):
    phi, rewards, nphi, nv = make_arrays(30)
    target = tmp_path / "w"
    w = DatasetWriter(target, horizon=H, n_features=D, n_actions=A)
    w.append(phi[:10], rewards[:10], nphi[:10])
    bad = phi[10:20].copy()
    bad[3, 1, 2] = np.nan
    with pytest.raises(ValueError, match="phi contains 1 NaN"):
        w.append(bad, rewards[10:20], nphi[10:20])
    with pytest.raises(ValueError, match=r"next_phi must have shape \(k, H, A, d\)"):
        w.append(phi[10:20], rewards[10:20], nphi[10:20, :, :2])
    with pytest.raises(ValueError, match="rewards must have shape"):
        w.append(phi[10:20], rewards[:3], nphi[10:20])
    with pytest.raises(TypeError, match="phi must be a numeric"):
        w.append(phi.astype(object), rewards, nphi)
    assert not target.exists()  # nothing at the path before close
    w.append(phi[10:], rewards[10:], nphi[10:], nv[10:])  # next_values in one chunk only
    assert w.close() == target
    ds = OfflineDataset.open(target)
    assert ds.dtype == np.float32 and ds.has_known_values
    assert np.isnan(ds.next_values[:10]).all()
    np.testing.assert_array_equal(ds.next_values[10:, : H - 1], nv[10:, : H - 1])
    np.testing.assert_array_equal(ds.phi, phi.astype(np.float32))
    with pytest.raises(RuntimeError, match="closed"):
        w.append(phi, rewards, nphi)
    with pytest.raises(FileExistsError):
        DatasetWriter(target, horizon=H, n_features=D, n_actions=A)
    with pytest.raises(RuntimeError, match="boom"):  # an error inside `with` discards all
        with DatasetWriter(tmp_path / "x", horizon=H, n_features=D, n_actions=A) as w2:
            w2.append(phi, rewards, nphi)
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]  # no temporary left behind
    with pytest.raises(ValueError, match="no trajectories"):
        DatasetWriter(tmp_path / "e", horizon=H, n_features=D, n_actions=A).close()
    with pytest.raises(ValueError, match="dtype"):
        DatasetWriter(tmp_path / "f", horizon=H, n_features=D, n_actions=A, dtype="int8")
    with pytest.raises(ValueError, match="dtype"):
        DatasetWriter(tmp_path / "g", horizon=H, n_features=D, n_actions=A, dtype="bogus")


def test_writer_warns_once_off_the_simplex(tmp_path):
    phi, rewards, nphi, _ = make_arrays(10)
    with DatasetWriter(tmp_path / "s", horizon=H, n_features=D, n_actions=A) as w:
        for _ in range(3):
            w.append(2 * phi, rewards, nphi)
        with pytest.warns(r2pvi.SimplexFeatureWarning) as record:
            w.close()
    assert len(record) == 1


def test_a_dropped_writer_leaves_nothing_behind(tmp_path):
    import gc

    w = DatasetWriter(tmp_path / "gone", horizon=H, n_features=D, n_actions=A)
    w.append(*make_arrays(5)[:3])
    assert len(list(tmp_path.iterdir())) == 1  # the temporary directory
    del w
    gc.collect()
    assert list(tmp_path.iterdir()) == []


def test_empty_append_with_mismatched_fields_is_refused(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2) as w:
        phi, rewards, next_phi = small_arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but rewards"):
            w.append(phi[:0], rewards, next_phi[:0])
        w.append(phi, rewards, next_phi)


def test_writer_records_reward_noise_and_empty_appends_check_next_values(tmp_path):
    with DatasetWriter(tmp_path / "w", horizon=3, n_features=4, n_actions=2,
                       reward_noise=0.1) as w:
        phi, rewards, next_phi = small_arrays(3)
        with pytest.raises(ValueError, match="0 trajectories but next_values"):
            w.append(phi[:0], rewards[:0], next_phi[:0], next_values=np.zeros((7, 1)))
        w.append(phi, rewards, next_phi)
    assert OfflineDataset.open(tmp_path / "w").reward_noise == 0.1
