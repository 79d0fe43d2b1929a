"""The command line: parser and dispatch."""

from tactiled.cli.parser import main

__all__ = ["main"]
