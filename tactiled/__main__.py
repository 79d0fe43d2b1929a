"""``python -m tactiled``: the command line as a process (:func:`tactiled.cli.entry.run`: :func:`tactiled.cli.main.main`, its
return value the exit code)."""

from tactiled.cli.entry import run

run()
