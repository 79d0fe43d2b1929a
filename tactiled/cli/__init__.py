"""The command line: ``main.py`` parses and dispatches; a module per group of commands (``cmd_*.py``) holds each
command's options and the one library call it makes; ``clidoc.py`` writes docs/cli.md from the parser; ``entry.py`` is
the process's entry point, which imports the rest only once it can take a Ctrl-C (so this package imports nothing)."""
