"""Optional dependencies in tests: skipped without them locally, required in CI."""

import importlib
import os

import pytest

REQUIRE_EXTRAS = bool(os.environ.get("CI") or os.environ.get("R2PVI_REQUIRE_EXTRAS"))


def require(module):
    """Import an optional dependency: skip without it, unless CI demands the extras."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if REQUIRE_EXTRAS:
            raise
        pytest.skip(f"optional dependency {module!r} is not installed ({exc})")
