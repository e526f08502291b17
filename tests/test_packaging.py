"""The package as users get it: install lines that work, one version, release metadata, CI.

Building the sdist and wheel and installing the wheel into a fresh virtual environment is
.ci/check-package's job (run by .ci/run after the test suite); these tests check the sources.
"""

import re
import shlex
import tomllib
from pathlib import Path

import pytest

import r2pvi

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PROJECT = PYPROJECT["project"]
EXTRAS = set(PROJECT["optional-dependencies"])
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
        *sorted((ROOT / "docs" / "user_guide").glob("*.md")),
        ROOT / "examples" / "GALLERY_HEADER.rst"]
REQUIREMENT = re.compile(r"(?P<name>[A-Za-z0-9_.-]+)(\[(?P<extras>[^\]]*)\])?(?P<rest>.*)",
                         re.S)


def _install_commands(text):
    """Every ``pip install ...`` command, with the line it is on."""
    for line in text.splitlines():
        for match in re.finditer(r"pip install ([^`#&\n]*)", line):
            yield match.group(1).strip().rstrip(".,;:)"), line


def _targets(args):
    """What a pip install command installs (its options dropped)."""
    return [a for a in shlex.split(args) if not a.startswith("-")]


def _problem(target, line):
    """Why ``pip install target`` would not work as written, or None."""
    path, _, extras = target.partition("[")
    extras = extras.rstrip("]")
    local = path in (".", "..") or path.startswith(("./", "/", "dist/")) or path.endswith(".whl")
    if not local:
        match = REQUIREMENT.fullmatch(target)
        if match is None:
            return "not a requirement"
        if match.group("name").lower() != "r2pvi":
            return None  # a package from PyPI (build, twine, minari[create], ...)
        extras = match.group("extras") or ""
        rest = match.group("rest").strip()
        if rest.startswith("@"):
            if not rest.lstrip("@ ").startswith("file://"):
                return "a direct reference other than a file:// URL"
        elif "installed" not in line:
            # r2pvi is not on PyPI: the bare name works only to add an extra to an
            # installed r2pvi, and the line must say so
            return "r2pvi is not on PyPI: install from a clone ('.') or a wheel"
    if path.endswith(".whl"):
        wheel = Path(path).name
        if not wheel.startswith(f"r2pvi-{PROJECT['version']}-"):
            return f"wheel {wheel} is not version {PROJECT['version']}"
    unknown = {e.strip() for e in extras.split(",") if e.strip()} - EXTRAS
    if unknown:
        return f"no extra {sorted(unknown)} in pyproject.toml"
    return None


def test_every_install_line_in_the_docs_works_from_a_clone_or_a_wheel():
    problems, seen = [], 0
    for doc in DOCS:
        for args, line in _install_commands(doc.read_text()):
            for target in _targets(args):
                seen += 1
                why = _problem(target, line)
                if why:
                    problems.append(f"{doc.relative_to(ROOT)}: pip install {args!r}: {why}")
    assert seen >= 15
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("line, ok", [
    ("pip install r2pvi", False),                                  # not on PyPI
    ("pip install 'r2pvi[gym]'", False),
    ("pip install 'r2pvi[gym]' once r2pvi is installed", True),
    ("pip install '.[experiments]'", True),
    ("pip install -e '.[test]'", True),
    ("pip install '.[gmy]'", False),                               # no such extra
    ("pip install 'dist/r2pvi-0.0.1-py3-none-any.whl'", False),    # another version
    ("pip install 'r2pvi[gym] @ file:///tmp/r2pvi.whl'", True),
    ("pip install 'r2pvi[gym] @ https://example.org/r2pvi.whl'", False),
    ("pip install 'minari[create]'", True),
])
def test_install_line_check_tells_working_lines_from_failing_ones(line, ok):
    (args, text), = _install_commands(line)
    assert all(_problem(t, text) is None for t in _targets(args)) is ok


def test_the_version_is_set_in_pyproject_only():
    assert r2pvi.__version__ == PROJECT["version"], (
        "the installed metadata is stale: reinstall (pip install -e .)")
    assert re.fullmatch(r"\d+\.\d+\.\d+", PROJECT["version"])
    for path in (ROOT / "src").rglob("*.py"):
        text = path.read_text()
        assert PROJECT["version"] not in text or path.name == "minari.py", path
        # no second copy (the fallback for a source tree without metadata aside)
        assert not re.search(r"__version__ = \"(?!0\.0\.0\+unknown)", text), path
    assert "r2pvi.__version__" in (ROOT / "docs" / "conf.py").read_text()


def test_release_metadata():
    assert PROJECT["license"] == "MIT"  # an SPDX expression, not a table
    assert PROJECT["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License\n")
    classifiers = PROJECT["classifiers"]
    assert not [c for c in classifiers if c.startswith("License ::")]  # PEP 639: expression
    low = int(re.fullmatch(r">=3\.(\d+)", PROJECT["requires-python"]).group(1))
    versions = [int(c.rsplit(".", 1)[1]) for c in classifiers
                if re.fullmatch(r"Programming Language :: Python :: 3\.\d+", c)]
    assert versions and min(versions) == low
    for name, url in PROJECT.get("urls", {}).items():  # no invented or placeholder URLs
        assert url.startswith("https://") and not re.search(
            r"example|todo|your|<|>|xxx", url, re.I), (name, url)
    assert set(PROJECT["optional-dependencies"]["release"]) >= {"build>=1.2", "twine>=6.1"}


def test_changelog_keeps_a_changelog():
    text = (ROOT / "CHANGELOG.md").read_text()
    assert text.startswith("# Changelog\n")
    assert "https://keepachangelog.com/en/1.1.0/" in text
    headings = re.findall(r"^## \[([^\]]+)\]", text, re.M)
    assert headings[0] == "Unreleased"
    for version in headings[1:]:  # released versions, newest first, none above pyproject's
        assert tuple(map(int, version.split("."))) <= tuple(
            map(int, PROJECT["version"].split(".")))
    sections = re.findall(r"^### (\w+)", text, re.M)
    assert set(sections) <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}


def test_ci_checks_the_built_package_after_the_readme_test_command():
    ci = "\n".join(line for line in (ROOT / ".ci" / "run").read_text().splitlines()
                   if not line.startswith("#"))
    tests = ci.index("pip install -e '.[test]' && python -m pytest")
    assert tests < ci.index(".ci/check-package") < ci.index("sphinx")
    check = (ROOT / ".ci" / "check-package").read_text()
    for step in ("python -m build", "twine check --strict", "python -m venv",
                 "r2pvi\" --version", "r2pvi\" -V", "unset PYTHONPATH", "r2pvi[gym]"):
        assert step in check, step


def test_gamma_is_introduced_as_the_ridge_parameter_not_a_discount_on_every_page():
    # RL readers take gamma for a discount; r2pvi's gamma is the paper's ridge parameter
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "docs" / "user_guide").glob("*.md"))]
    checked = 0
    for page in pages:
        text = " ".join(page.read_text().replace("#", " ").split())
        first = re.search(r"\bgamma\b", text)
        if first is None:
            continue
        checked += 1
        near = text[max(0, first.start() - 200): first.start() + 1000]
        assert "ridge parameter" in near and "not a discount" in near, page.name
    assert checked >= 10
