"""The README's code block runs as written, and its test command is the one CI runs."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks
    monkeypatch.chdir(tmp_path)
    for code in blocks:
        exec(compile(code, "README.md", "exec"), {})
    assert (tmp_path / "model.npz").exists()


def test_ci_runs_the_readme_test_command():
    text = (ROOT / "README.md").read_text()
    command = re.search(r"^(pip install -e '\.\[test\]' && python -m pytest)", text, re.M).group(1)
    ci = (ROOT / ".ci" / "run").read_text()
    assert command in ci
