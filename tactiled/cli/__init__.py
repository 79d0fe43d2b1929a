"""The command line: ``main.py`` parses and dispatches; a module per group of commands (``cmd_*.py``) holds each
command's options and the one library call it makes; ``clidoc.py`` writes docs/cli.md from the parser."""

from tactiled.cli.main import main

__all__ = ["main"]
