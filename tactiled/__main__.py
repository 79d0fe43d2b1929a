"""``python -m tactiled``: the command line as a process (:func:`tactiled.cli.main.run`: :func:`tactiled.cli.main`, its return value the exit code)."""

from tactiled.cli.main import run

run()
