"""The documentation sources: gallery scripts that sphinx-gallery can render and that pytest
does not collect; generated output kept out of git."""

import ast
import re
import tomllib
from pathlib import Path

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
