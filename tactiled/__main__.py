"""``python -m tactiled``: the command line (:func:`tactiled.cli.main`), its return value the exit code."""

import sys

from tactiled.cli import main

sys.exit(main())
