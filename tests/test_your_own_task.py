"""The "Your own task" guide (docs/your-own-task.md) runs as written, block after block."""

import re
from pathlib import Path

from extras import require

DOCS = Path(__file__).resolve().parents[1] / "docs" / "your-own-task.md"


def test_guide_runs(tmp_path, monkeypatch, capsys):
    for module in ("gymnasium", "minari", "h5py", "PIL"):
        require(module)
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    assert len(blocks) >= 6
    monkeypatch.chdir(tmp_path)
    # the guide points Minari's root at a fresh directory: restored after the test
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    namespace = {}
    for block in blocks:
        exec(compile(block, str(DOCS), "exec"), namespace)  # noqa: S102
    out = capsys.readouterr().out
    assert "rewards go down to -1" in out and "0.0 0.0" in out
    assert "60 True" in out
    assert "20 100" in out  # Minari's create_dataset_from_buffers, read back by from_minari
