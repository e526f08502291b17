"""``python -m r2pvi`` is the ``r2pvi`` command."""

import sys

from .cli import main

sys.exit(main())
