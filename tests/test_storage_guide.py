"""The storage guide (docs/storage.md) runs as written: write, open, fit, convert, verify."""

import re
from pathlib import Path

from extras import require

DOCS = Path(__file__).resolve().parents[1] / "docs" / "storage.md"


def test_storage_guide_runs_block_after_block(tmp_path, monkeypatch, capsys):
    require("dask")
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    assert len(blocks) >= 7  # write (2), open, fit, convert (2), verify
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for block in blocks:
        exec(compile(block, str(DOCS), "exec"), namespace)  # noqa: S102
    out = capsys.readouterr().out
    assert "'manifest.json'" in out and "'phi.npy'" in out
    assert "disk 500 4 5 2" in out and "disk float32" in out
    assert "True\nTrue\n" in out  # the fits from disk equal the in-memory fit
    assert "memory memory 250" in out and "dask True" in out
    # episodes of a crossed map: state features on disk, fitted as in memory
    assert "['actions.npy', 'next_values.npy', 'psi.npy', 'rewards.npy']\ndisk True" in out
    for path in ("demo-data", "demo-stream", "demo-half", "demo-from-dask", "demo-episodes"):
        assert (tmp_path / path / "manifest.json").is_file()


def test_storage_guide_shows_the_errors_its_blocks_raise(tmp_path, monkeypatch, capsys):
    """The error messages printed in the guide are those its own blocks print."""
    require("dask")
    text = DOCS.read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    shown = re.search(r"```text\n(demo-data exists.*?)```", text, flags=re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for block in blocks:
        exec(compile(block, str(DOCS), "exec"), namespace)  # noqa: S102
    printed = capsys.readouterr().out.splitlines()
    for line in shown.splitlines():
        prefix = line.removesuffix("...")
        assert any(p.startswith(prefix) for p in printed), line
