"""The documentation sources: gallery scripts that sphinx-gallery can render and that pytest
does not collect; generated output kept out of git; snippets that run as written and guides
that show what the library does (sparse rows, ``OfflineDataset.load``)."""

import ast
import re
import tomllib
from pathlib import Path

from extras import require

ROOT = Path(__file__).resolve().parents[1]


def test_gallery_scripts_have_a_title_and_are_not_collected_by_pytest():
    scripts = sorted((ROOT / "examples").glob("plot_*.py"))
    assert len(scripts) >= 6
    for path in scripts:
        doc = ast.get_docstring(ast.parse(path.read_text()))
        assert doc, f"{path.name}: sphinx-gallery needs a docstring"
        title, underline = doc.splitlines()[:2]
        assert re.fullmatch(r"=+", underline) and len(underline) >= len(title), path.name
    assert (ROOT / "examples" / "GALLERY_HEADER.rst").exists()
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]
    assert "examples" not in " ".join(config["ini_options"]["testpaths"])
    assert {"examples", "auto_examples", "_build"} <= set(config["ini_options"]["norecursedirs"])
    ignored = (ROOT / ".gitignore").read_text().split()
    assert {"docs/_build/", "docs/auto_examples/", "docs/generated/"} <= set(ignored)


def test_large_feature_spaces_snippet_runs_as_written(capsys):
    require("gymnasium")
    text = (ROOT / "docs" / "large-feature-spaces.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks
    for code in blocks:
        exec(compile(code, "large-feature-spaces.md", "exec"), {})  # noqa: S102
    assert "memory (sparse rows) 10000 (20, 10000)" in capsys.readouterr().out


def test_the_guide_shows_sparse_rows_and_the_readme_shows_load():
    guide = (ROOT / "docs" / "your-own-task.md").read_text()
    assert "dense\nfor now" not in guide and "sparse engine path is planned" not in guide
    assert "SparseOfflineDataset" in guide
    assert "OfflineDataset.load(path)" in (ROOT / "README.md").read_text()


def test_the_front_page_examples_run_and_the_episode_one_is_pooled():
    require("gymnasium")
    text = (ROOT / "docs" / "index.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 2
    first: dict = {}
    exec(compile(blocks[0], "index.md", "exec"), first)  # noqa: S102
    assert first["data"].stationary
    exec(compile(blocks[1], "index.md", "exec"), {})  # noqa: S102
