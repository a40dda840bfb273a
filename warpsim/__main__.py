"""``python -m warpsim``: the command line (see warpsim.cli)."""
import sys

from .cli import main

sys.exit(main())
