"""Dataset directories: saved by ``OfflineDataset.save``, opened lazily by ``open``.

The format is documented (``r2pvi.storage``): step-major ``.npy`` files and a JSON manifest
that records what a fit needs without reading the data (the Gram matrices, checked on open).
Opening refuses a missing, empty, foreign, future or truncated directory; a next-state table
round-trips without storing a row per sample. Damaged and hand-edited directories are tested
in test_damaged_files.py, overwrites in test_save_never_destroys.py, the writer in
test_dataset_writer.py.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from storage_helpers import (
    ESTIMATORS,
    D,
    H,
    K,
    assert_same_fit,
    make_arrays,
    small_arrays,
)

from r2pvi import DatasetWriter, OfflineDataset


def test_directory_format_is_documented_step_major_and_lazy(stored):
    mem, saved, written = stored
    manifest = json.loads((saved / "manifest.json").read_text())
    assert manifest["kind"] == "r2pvi.OfflineDataset" and manifest["format_version"] == 2
    assert manifest["layout"] == "step-major" and manifest["next"] == "stored"
    raw = np.load(saved / "phi.npy", allow_pickle=False)
    assert raw.shape == (H, K, D)
    np.testing.assert_array_equal(raw, mem.phi.transpose(1, 0, 2))
    ds = OfflineDataset.open(written)
    assert isinstance(ds.phi.base, np.memmap) or isinstance(ds.phi, np.memmap)
    for name in ("phi", "rewards", "next_values"):
        np.testing.assert_array_equal(getattr(ds, name), getattr(mem, name))
    np.testing.assert_array_equal(ds.next_phi[:, : H - 1], mem.next_phi[:, : H - 1])
    assert ds.nonnegative_features and ds.nonnegative_next_features
    sub = ds.subset([3, 1])
    assert sub.storage == "memory"
    np.testing.assert_array_equal(sub.phi, mem.phi[[3, 1]])


def test_open_rejects_foreign_future_missing_and_truncated(tmp_path):
    ds = OfflineDataset.from_features(*make_arrays(20)[:3])
    path = ds.save(tmp_path / "d")
    with pytest.raises(FileNotFoundError):
        OfflineDataset.open(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no manifest.json"):
        OfflineDataset.open(tmp_path / "empty")
    mf = json.loads((path / "manifest.json").read_text())
    (path / "manifest.json").write_text(json.dumps({**mf, "format_version": 99}))
    with pytest.raises(ValueError, match="format version 99"):
        OfflineDataset.open(path)
    (path / "manifest.json").write_text(json.dumps(mf))
    with open(path / "phi.npy", "r+b") as fh:
        fh.truncate(os.path.getsize(path / "phi.npy") - 8)
    with pytest.raises(ValueError, match="truncated"):
        OfflineDataset.open(path)
    with pytest.raises(FileExistsError):
        ds.save(path)
    ds.save(path, overwrite=True)
    assert OfflineDataset.open(path).n_trajectories == 20


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Other numbers (seed 3) in memory and saved as a directory."""
    phi, rewards, nphi, nv = make_arrays(seed=3)
    mem = OfflineDataset.from_features(phi, rewards, nphi, nv)
    return mem, mem.save(tmp_path_factory.mktemp("stream") / "ds")


def test_gram_matrices_are_stored_with_the_data_and_checked(saved, tmp_path):
    mem, path = saved
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["files"]["gram"] == "gram.npy"
    grams = np.load(path / "gram.npy")
    phi = mem.phi
    for h in range(mem.horizon):
        np.testing.assert_allclose(grams[h], phi[:, h].T @ phi[:, h], rtol=1e-12)
    # float32 storage: the Gram matrices are those of the rounded features that are stored
    f32 = mem.save(tmp_path / "f32", dtype="float32")
    x = OfflineDataset.open(f32).phi[:, 0].astype(np.float64)
    np.testing.assert_allclose(np.load(f32 / "gram.npy")[0], x.T @ x, rtol=1e-12)
    np.save(f32 / "gram.npy", grams[:, :2])  # the wrong shape
    with pytest.raises(ValueError, match="Gram matrices"):
        OfflineDataset.open(f32)


def test_table_dataset_round_trips_through_the_directory_format(tmp_path):
    table = np.random.default_rng(0).dirichlet(np.ones(3), size=(5, 2))
    idx = np.random.default_rng(1).integers(5, size=(40, 3))
    act = np.random.default_rng(2).integers(2, size=(40, 3))
    known = np.full((5, 2), np.nan)
    known[4] = 0.0
    ds = OfflineDataset.from_next_state_table(table[idx, act], idx[:, ::-1] * 0.1, idx, table,
                                              known, actions=act)
    back = OfflineDataset.open(ds.save(tmp_path / "t"))
    assert json.loads((tmp_path / "t" / "manifest.json").read_text())["next"] == "table"
    assert not (tmp_path / "t" / "next_phi.npy").exists()  # nothing per sample but an index
    np.testing.assert_array_equal(back.actions, act)
    assert_same_fit(ESTIMATORS["KL"]().fit(back), ESTIMATORS["KL"]().fit(ds))
    with pytest.raises(ValueError, match=r"next_states must lie in \[0, 5\)"):
        OfflineDataset.from_next_state_table(table[idx, act], idx * 0.1, idx + 1, table)
    with pytest.raises(ValueError, match="known_values must have shape"):
        OfflineDataset.from_next_state_table(table[idx, act], idx * 0.1, idx, table, known[:2])


def test_float32_save_refuses_finite_values_beyond_its_range(tmp_path):
    """Finite values beyond float32's range (which would become inf, the Gram matrices and the
    fits NaN) are refused before anything is written, by the save, by ``from_features`` with
    ``dtype="float32"`` and by the writer's append, which leaves the writer usable."""
    phi, rewards, next_phi = small_arrays(10)
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
        w.append(*small_arrays(5))
    assert OfflineDataset.open(tmp_path / "w").n_trajectories == 5
