"""Step-major storage: the names of :mod:`r2pvi.data.storage`, kept importable from here."""

from .data.storage import *  # noqa: F401,F403
from .data.storage import __all__  # noqa: F401
