"""A save never destroys what r2pvi did not write.

Without ``overwrite`` a save refuses an existing path. With ``overwrite=True`` a dataset save
replaces an r2pvi dataset and nothing else: a user's directory or file at the path survives
byte for byte, a failed save keeps the old dataset, and what a killed save left behind is
cleaned on the next open or write of the path. An estimator's save never writes over a
dataset file or directory, nor over a file r2pvi did not write; a model replaces a model."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import r2pvi
from r2pvi import PEVI, DatasetWriter, OfflineDataset
from r2pvi.sparse import SparseOfflineDataset

K, H, A, D = 12, 3, 2, 4
SRC = str(Path(r2pvi.__file__).resolve().parents[1])  # children import the same r2pvi


def _data(seed=0):
    rng = np.random.default_rng(seed)
    return OfflineDataset.from_features(rng.dirichlet(np.ones(D), (K, H)), rng.random((K, H)),
                                        rng.dirichlet(np.ones(D), (K, H, A)))


def _snapshot(root: Path) -> dict:
    """Every file under ``root`` (relative path -> bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def _user_directory(path: Path) -> dict:
    path.mkdir()
    (path / "thesis.tex").write_text("\\section{Results}\n")
    (path / "runs").mkdir()
    (path / "runs" / "seed0.csv").write_text("step,return\n0,1.5\n")
    return _snapshot(path)


def _writer(path, **kw):
    return DatasetWriter(path, horizon=H, n_features=D, n_actions=A, **kw)


SAVES = {
    "save": lambda data, path: data.save(path, overwrite=True),
    "DatasetWriter": lambda data, path: _writer(path, overwrite=True),
}


@pytest.mark.parametrize("how", sorted(SAVES))
def test_overwrite_refuses_a_user_directory_and_it_survives(tmp_path, how):
    target = tmp_path / "results"
    before = _user_directory(target)
    with pytest.raises(FileExistsError, match="results.*not an r2pvi dataset.*thesis.tex"):
        SAVES[how](_data(), target)
    assert _snapshot(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]  # no temporary left


@pytest.mark.parametrize("how", sorted(SAVES))
@pytest.mark.parametrize("content", [b"my notes\n", b""], ids=["foreign", "empty"])
def test_overwrite_refuses_a_user_file_and_it_survives(tmp_path, how, content):
    target = tmp_path / "notes"
    target.write_bytes(content)
    what = "a file r2pvi did not write" if content else "an empty file"
    with pytest.raises(FileExistsError, match=f"notes exists and holds {what}"):
        SAVES[how](_data(), target)
    assert target.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes"]


def test_overwrite_refuses_a_dataset_directory_holding_a_user_file(tmp_path):
    target = _data().save(tmp_path / "ds")
    (target / "README.txt").write_text("collected on the robot, 2024\n")
    before = _snapshot(target)
    for save in SAVES.values():
        with pytest.raises(FileExistsError, match="entry r2pvi did not write.*README.txt"):
            save(_data(1), target)
    assert _snapshot(target) == before


def test_npz_save_refuses_a_foreign_file_with_overwrite(tmp_path):
    target = tmp_path / "mine.npz"
    np.savez(target, a=np.arange(3))
    before = target.read_bytes()
    with pytest.raises(FileExistsError, match="r2pvi did not write"):
        _data().save(target, overwrite=True)
    assert target.read_bytes() == before


@pytest.mark.parametrize("how", sorted(SAVES))
def test_overwrite_replaces_a_dataset_an_old_dataset_file_or_an_empty_directory(tmp_path, how):
    new = _data(1)

    def save(path):
        if how == "save":
            return new.save(path, overwrite=True)
        with _writer(path, overwrite=True, dtype="float64") as w:
            w.append(new.phi, new.rewards, new.next_phi)
        return path

    directory = _data().save(tmp_path / "dir")
    single = tmp_path / "single"
    _data().save(tmp_path / "single.npz").rename(single)  # the single-file format
    (tmp_path / "empty").mkdir()
    for path in (directory, single, tmp_path / "empty"):
        save(path)
        assert np.array_equal(OfflineDataset.open(path).phi, new.phi)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "empty", "single"]


def test_a_path_taken_before_the_rename_is_refused_at_the_rename(tmp_path):
    target = tmp_path / "out"
    data = _data()
    with _writer(target, overwrite=True) as w:  # nothing at the path yet
        w.append(data.phi, data.rewards, data.next_phi)
        before = _user_directory(target)  # the user's directory appears meanwhile
        with pytest.raises(FileExistsError, match="not an r2pvi dataset"):
            w.close()
    assert _snapshot(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_save_that_fails_at_the_swap_keeps_the_old_dataset(tmp_path, monkeypatch):
    old, new = _data(0), _data(1)
    target = old.save(tmp_path / "ds")
    before = _snapshot(target)
    real = os.replace

    def failing(src, dst):  # the old dataset is moved aside, then the new one cannot move in
        if ".tmp-" in str(src):
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)  # the rename r2pvi's saves make
    with pytest.raises(OSError, match="No space left"):
        new.save(target, overwrite=True)
    monkeypatch.undo()
    assert _snapshot(target) == before
    assert np.array_equal(OfflineDataset.open(target).phi, old.phi)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_sparse_dataset_save_takes_the_save_keywords_and_touches_nothing(tmp_path):
    import scipy.sparse as sp

    rng = np.random.default_rng(0)
    rows = [sp.csr_matrix(rng.random((K, D))) for _ in range(H)]
    nxt = [sp.csr_matrix(rng.random((K * A, D))) for _ in range(H)]
    ds = SparseOfflineDataset.from_rows(rows, rng.random((K, H)), nxt, A)
    target = tmp_path / "kept"
    before = _user_directory(target)
    with pytest.raises(TypeError, match="cannot save a dataset of sparse rows.*kept"):
        ds.save(target, overwrite=True)
    with pytest.raises(TypeError, match="cannot save a dataset of sparse rows"):
        ds.save(tmp_path / "new", dtype="float32", next_form="full")
    assert _snapshot(target) == before and not (tmp_path / "new").exists()


# ---------------------------------------------------------------- without overwrite, models
def test_dataset_npz_save_refuses_an_existing_file_unless_overwrite(tmp_path):
    data = _data()
    other = _data(seed=1)
    path = data.save(tmp_path / "x.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        other.save(path)
    assert path.read_bytes() == before
    other.save(path, overwrite=True)
    assert np.array_equal(OfflineDataset.load(path).phi, other.phi)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npz"]  # no temporary left


def test_estimator_save_never_writes_over_a_dataset_or_a_directory(tmp_path):
    data = _data()
    est = PEVI().fit(data)
    folder = data.save(tmp_path / "mem_dir")
    with pytest.raises(IsADirectoryError, match="dataset directory.*mem_dir.npz"):
        est.save(folder)
    assert not (tmp_path / "mem_dir.npz").exists()
    kept = data.save(tmp_path / "data.npz")
    before = kept.read_bytes()
    with pytest.raises(FileExistsError, match="holds a dataset"):
        est.save(kept)
    assert kept.read_bytes() == before
    foreign = tmp_path / "mine.npz"
    np.savez(foreign, a=np.ones(3))
    with pytest.raises(FileExistsError, match="r2pvi did not write"):
        est.save(foreign)
    (tmp_path / "empty.npz").touch()  # an empty file (tempfile's) holds nothing to lose
    assert r2pvi.load(est.save(tmp_path / "empty.npz")).n_actions_ == A
    model = est.save(tmp_path / "model.npz")
    PEVI(beta=0.5).fit(data).save(model)  # a model replaces a model
    assert r2pvi.load(model).beta == 0.5


def test_directory_save_over_a_dataset_file_leaves_nothing_behind(tmp_path):
    data = _data()
    path = tmp_path / "d"
    data.save(path.with_suffix(".npz")).rename(path)  # a dataset file without a suffix
    with pytest.raises(FileExistsError):
        data.save(path)
    data.save(path, overwrite=True)
    assert path.is_dir() and sorted(p.name for p in tmp_path.iterdir()) == ["d"]


_NAMES = st.text("abcxyz_.-0123456789", min_size=1, max_size=8).filter(
    lambda s: s not in (".", ".."))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(files=st.dictionaries(_NAMES, st.binary(max_size=64), min_size=1, max_size=5),
       dataset=st.booleans())
def test_any_directory_with_foreign_entries_survives_an_overwrite(files, dataset):
    data = _data()
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / "d"
        if dataset:  # a dataset directory the user added files to
            data.save(target)
            own = {p.name for p in target.iterdir()}
            files = {k: v for k, v in files.items() if k not in own} or {"extra": b"x"}
        else:
            target.mkdir()
        for name, content in files.items():
            (target / name).write_bytes(content)
        before = _snapshot(target)
        for save in SAVES.values():
            with pytest.raises(FileExistsError, match="r2pvi did not write|not an r2pvi"):
                save(data, target)
        assert _snapshot(target) == before
        assert sorted(p.name for p in Path(tmp).iterdir()) == ["d"]


# ---------------------------------------------------------------- killed saves
def _run_child(code: str, wait: bool = True):
    env = {**os.environ, "PYTHONPATH": SRC}
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    if wait:
        proc.wait(timeout=120)
    return proc


def _side_entries(folder: Path, name: str, kind: str) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(f".{name}.{kind}-"))


_APPEND_THEN_DIE = """
    import os, signal, numpy as np
    from r2pvi import DatasetWriter
    rng = np.random.default_rng(0)
    w = DatasetWriter({path!r}, horizon={H}, n_features={D}, n_actions={A})
    w.append(rng.dirichlet(np.ones({D}), ({K}, {H})), rng.random(({K}, {H})),
             rng.dirichlet(np.ones({D}), ({K}, {H}, {A})))
    {then}
"""


def test_a_temporary_left_by_a_killed_append_is_removed_by_the_next_write(tmp_path):
    target = tmp_path / "ds"
    kw = {"path": str(target), "H": H, "D": D, "A": A, "K": K}
    # a live writer of the same path, whose temporary must never be touched
    live = _run_child(_APPEND_THEN_DIE.format(**kw, then="print('ready', flush=True); input()"),
                      wait=False)
    try:
        assert live.stdout.readline().strip() == "ready"
        mine = _side_entries(tmp_path, "ds", "tmp")
        assert len(mine) == 1 and f"-{live.pid}-" in mine[0]
        proc = _run_child(_APPEND_THEN_DIE.format(
            **kw, then="os.kill(os.getpid(), signal.SIGKILL)"))
        assert proc.returncode == -signal.SIGKILL
        left = [n for n in _side_entries(tmp_path, "ds", "tmp") if f"-{proc.pid}-" in n]
        assert len(left) == 1  # kill -9 mid-append leaves its temporary directory
        data = _data()
        with _writer(target) as w:  # the next write of the path
            w.append(data.phi, data.rewards, data.next_phi)
        assert _side_entries(tmp_path, "ds", "tmp") == mine  # the killed one is gone
        assert OfflineDataset.open(target).n_trajectories == K
    finally:
        live.communicate("\n", timeout=120)
    assert _side_entries(tmp_path, "ds", "tmp") == []  # the live one removed its own


def test_opening_the_path_after_a_killed_append_cleans_it(tmp_path):
    target = tmp_path / "ds"
    kw = {"path": str(target), "H": H, "D": D, "A": A, "K": K}
    _run_child(_APPEND_THEN_DIE.format(**kw, then="os.kill(os.getpid(), signal.SIGKILL)"))
    assert len(_side_entries(tmp_path, "ds", "tmp")) == 1
    with pytest.raises(FileNotFoundError):
        OfflineDataset.open(target)
    assert list(tmp_path.iterdir()) == []


def test_an_overwrite_killed_mid_swap_gives_the_old_dataset_back_on_open(tmp_path):
    old = _data(0)
    target = old.save(tmp_path / "ds")
    proc = _run_child(f"""
        import os, signal, numpy as np
        from r2pvi import OfflineDataset
        real = os.replace
        def replace(src, dst):
            if ".tmp-" in str(src):  # the old dataset moved aside: die before the new one lands
                os.kill(os.getpid(), signal.SIGKILL)
            return real(src, dst)
        os.replace = replace
        rng = np.random.default_rng(5)
        ds = OfflineDataset.from_features(rng.random(({K}, {H}, {D})), rng.random(({K}, {H})),
                                          rng.random(({K}, {H}, {A}, {D})), check_simplex=False)
        ds.save({str(target)!r}, overwrite=True)
    """)
    assert proc.returncode == -signal.SIGKILL
    assert not target.exists() and len(_side_entries(tmp_path, "ds", "old")) == 1
    assert np.array_equal(OfflineDataset.open(target).phi, old.phi)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
