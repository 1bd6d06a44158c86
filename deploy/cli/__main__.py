"""``python -m deploy.cli``: the ``omnifleet`` command (what the installed script runs)."""

import sys

from deploy.cli import main

sys.exit(main())
