"""``python -m rl_scan.cli``: the same as the ``rl-scan`` console script."""

import sys

from rl_scan.cli import main

sys.exit(main())
