"""``python -m plenoctree`` = the ``plenoctree`` command."""

import sys

from .cli import main

sys.exit(main())
