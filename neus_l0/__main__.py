"""``python -m neus_l0``: the same command line as the ``neus-l0`` script."""

import sys

from neus_l0.cli import main

sys.exit(main())
