"""Sphinx configuration of the r2pvi documentation.

Build: ``python -m sphinx -W --keep-going -b html docs docs/_build/html`` (warnings are
errors, as in CI). Why this stack (also on the installation page): Sphinx with numpydoc
renders the docstrings the code already has (numpydoc sections, runnable Examples),
autosummary turns every public name into a reference page, sphinx-gallery runs the scripts
in ``examples/`` at build time (so every picture in the gallery is produced by the code of
its release), and myst-parser keeps the reproduction, theory and environment pages in the
markdown the repository already uses. These are the tools of scikit-learn, d3rlpy and
Minari, the libraries RL researchers know.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# Build from this source tree (not an installed copy), without installing it.
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")

import r2pvi  # noqa: E402

try:  # one BLAS thread: on a busy CI machine multi-threaded BLAS busy-waits and turns the
    # CartPole example's small solves from milliseconds into tenths of seconds (measured:
    # 8 min instead of 15 s on 2 shared cores)
    from threadpoolctl import threadpool_limits

    _BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")
except ImportError:  # pragma: no cover - threadpoolctl comes with the experiments extra
    pass

project = "r2pvi"
author = "the r2pvi developers"
copyright = "2026, the r2pvi developers"
release = version = r2pvi.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "**.ipynb_checkpoints", "auto_examples/*.md5",
                    "auto_examples/*.py", "auto_examples/*.ipynb", "auto_examples/*.zip"]
templates_path = ["_templates"]

# --------------------------------------------------------------------------- API reference
autosummary_generate = True
autodoc_default_options = {"members": True, "inherited-members": False}
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks: set[str] = set()

# Modules documented in the API reference, in this order: the public API on ``api``, the
# internals (step rules, storage, experiment machinery) on ``api-internals``. A public name
# (in a module's __all__) is documented once, under the first module that exports it.
API_MODULES = [
    ("r2pvi", "Estimators, the dataset and divergences", "api"),
    ("r2pvi.features", "Feature maps", "api"),
    ("r2pvi.data", "The dataset and its checks", "api"),
    ("r2pvi.episodes", "Episodes of any length", "api"),
    ("r2pvi.sparse", "Sparse rows (tile coding, aggregation, one-hot)", "api"),
    ("r2pvi.envs", "Environments", "api"),
    ("r2pvi.envs.perturbations", "Perturbed classic-control environments", "api"),
    ("r2pvi.envs.noisy_cartpole", "The noisy CartPole protocol (RFQI/RFZI)", "api"),
    ("r2pvi.envs.cartpole_grid", "The noisy CartPole test grid", "api"),
    ("r2pvi.envs.noisy_cartpole_gym", "The noisy CartPole as a Gymnasium environment", "api"),
    ("r2pvi.evaluation", "Exact and Monte Carlo evaluation", "api"),
    ("r2pvi.theory", "Theory in practice", "api"),
    ("r2pvi.duals", "Dual formulas and expectation operators", "api"),
    ("r2pvi.algorithms", "Step rules and model files", "api-internals"),
    ("r2pvi.data.storage", "Storage kinds, the step source and the on-disk format",
     "api-internals"),
    ("r2pvi.experiments", "Reproducing the paper", "api-internals"),
]

API_PAGES = {
    "api": ("API reference",
            "The public API: estimators, the dataset, feature maps, environments, evaluation, "
            "theory and the dual formulas, from their docstrings (each formula names the "
            "paper's equation it implements). Internals (step rules, storage, experiment "
            "machinery) are on :doc:`api-internals`."),
    "api-internals": ("Internals",
                      "Building blocks for contributors and for extending r2pvi: the step "
                      "rules the estimators plug into the backward induction, the storage "
                      "kinds and on-disk format, and the experiment runner. The public API "
                      "is on :doc:`api`."),
}

# autosummary's one-line summaries end at the first period followed by a space that is not
# a known abbreviation; docstrings cite the paper's equations as "(eq. 4.3)", which must not
# end the line there ("KL (eq." was the summary of KLRule).
import sphinx.ext.autosummary as _autosummary  # noqa: E402

_autosummary.WELL_KNOWN_ABBREVIATIONS = (*_autosummary.WELL_KNOWN_ABBREVIATIONS, "(eq.", " eq.",
                                          "Eq.", "eqs.", "Sec.", "App.")


def _api_modules() -> list[tuple[str, str, str]]:
    """``API_MODULES`` plus any public subpackage it does not list yet (a new one appears in
    the internals without editing this file)."""
    import pkgutil

    listed = [name for name, _, _ in API_MODULES]
    extra = [(f"r2pvi.{m.name}", m.name, "api-internals")
             for m in pkgutil.iter_modules(r2pvi.__path__)
             if m.ispkg and not m.name.startswith("_") and f"r2pvi.{m.name}" not in listed]
    return API_MODULES + sorted(extra)


def _write_api_page() -> None:
    """Write ``api.rst`` and ``api-internals.rst`` from the modules' ``__all__``: a new public
    name appears without editing the docs, and nothing is documented twice."""
    seen: set[int] = set()
    pages = {}
    for page, (title, intro) in API_PAGES.items():
        pages[page] = [".. This file is generated by docs/conf.py from each module's __all__.",
                       "", title, "=" * len(title), "", intro, ""]
    for modname, title, page in _api_modules():
        try:
            module = importlib.import_module(modname)
        except ImportError:  # a subpackage that does not exist in this version
            continue
        names = []
        for name in getattr(module, "__all__", []):
            obj = getattr(module, name, None)
            if obj is None or name.startswith("__") or inspect.ismodule(obj):
                continue
            if not (inspect.isclass(obj) or inspect.isfunction(obj) or callable(obj)):
                continue  # constants are described in their module's docstring
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            names.append(name)
        if not names:
            continue
        pages[page] += [f"``{modname}``: {title}", "-" * (len(modname) + 6 + len(title)), "",
                        f".. automodule:: {modname}", "   :no-members:", "   :no-index:", "",
                        f".. currentmodule:: {modname}", "", ".. autosummary::",
                        "   :toctree: generated", "   :nosignatures:", ""]
        pages[page] += [f"   {n}" for n in names] + [""]
    for page, lines in pages.items():
        text = "\n".join(lines)
        path = HERE / f"{page}.rst"
        if not path.exists() or path.read_text() != text:
            path.write_text(text)


_write_api_page()

# --------------------------------------------------------------------------- gallery
sphinx_gallery_conf = {
    "examples_dirs": ["../examples"],
    "gallery_dirs": ["auto_examples"],
    "filename_pattern": r"/plot_",  # every plot_*.py runs at build time
    "ignore_pattern": r"__init__\.py|conftest\.py",
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "show_memory": False,
    "reset_modules": ("matplotlib",),
    "matplotlib_animations": False,
    "min_reported_time": 1,
    "image_scrapers": ("matplotlib",),
}

# --------------------------------------------------------------------------- markdown, html
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]
suppress_warnings = ["myst.header"]

html_theme = "pydata_sphinx_theme"
html_title = f"r2pvi {release}"
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "secondary_sidebar_items": ["page-toc"],
}
html_static_path: list[str] = []
html_show_sourcelink = False


# --------------------------------------------------------------------------- optional pages
# Pages other branches add (the architecture for contributors, the numerical guarantees, the
# classic-control benchmark, ...): a toctree line "OPTIONAL_PAGES" becomes the ones that exist,
# so the site includes them as soon as they are merged and builds without them meanwhile. The
# main index also picks up any other top-level page that no toctree lists yet.
OPTIONAL_PAGES = {
    "index": ["architecture"],
    "user_guide/index": ["../your-own-task", "../numerical-guarantees", "../classic-control",
                         "../storage"],
}


def _listed_pages() -> set[str]:
    """Top-level page names mentioned in the hand-written toctrees and OPTIONAL_PAGES."""
    names = {Path(p).name for pages in OPTIONAL_PAGES.values() for p in pages}
    for doc in ("index.md", "user_guide/index.md"):
        names |= {line.strip().removeprefix("../") for line in (HERE / doc).read_text()
                  .splitlines()}
    return names


def _optional_pages(app, docname, source):
    if docname not in OPTIONAL_PAGES:
        return
    base = (HERE / docname).parent
    present = [page for page in OPTIONAL_PAGES[docname]
               if (base / f"{page}.md").exists() or (base / f"{page}.rst").exists()]
    if docname == "index":
        listed = _listed_pages()
        present += sorted(p.stem for p in HERE.glob("*.md")
                          if p.stem not in listed and p.stem != "index")
    source[0] = source[0].replace("OPTIONAL_PAGES\n", "".join(f"{p}\n" for p in present))


def _reread_optional(app, env, added, changed, removed):
    return list(OPTIONAL_PAGES)  # an incremental build notices pages that came or went


def setup(app):
    app.connect("source-read", _optional_pages)
    app.connect("env-get-outdated", _reread_optional)
