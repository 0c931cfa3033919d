"""``python -m spinecohort``: the same command line as the ``spinecohort`` console script."""

import sys

from spinecohort.cli import main

sys.exit(main())
