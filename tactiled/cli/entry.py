"""The ``tactiled`` process's entry point (the console script, ``python -m tactiled``): :func:`run`.

It imports nothing of its own before it has a handler for Ctrl-C, so that a Ctrl-C while the command line's modules
load (a bare ``tactiled --help`` spends about 40 ms there) ends the process as one during a command does: exit 1,
no traceback. The interpreter's own start, before this module, is the only window left.
"""

from __future__ import annotations

import sys
from typing import NoReturn

EXIT_INTERRUPTED = 1  # as tactiled.cli.common.EXIT_FAIL, which a Ctrl-C during a command returns (not imported: it loads the config module)


def run() -> NoReturn:
    """:func:`tactiled.cli.main.run`, with a Ctrl-C at any moment (its imports, parsing, exit) one exit 1 without a traceback."""
    try:
        from tactiled.cli.main import run as run_command

        run_command()
    except KeyboardInterrupt:
        sys.exit(EXIT_INTERRUPTED)
