"""The ``tactiled`` command: ``main(argv) -> int``. It parses, calls one library function per command and prints;
each group of commands is a module of its own (``cmd_*.py``). Logging is configured here only.

Exit codes: 0 ok, 1 failure, 2 usage or bad input (config, recording, model, device path, output).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import sys
from collections.abc import Sequence
from typing import NoReturn

from tactiled import __version__
from tactiled.cli import cmd_files, cmd_learn, cmd_live, cmd_setup, cmd_simulate
from tactiled.cli.common import EXIT_FAIL, EXIT_USAGE, Handler, Parser, subcommands
from tactiled.errors import TactiledError

OUTPUT_POLICY = """\
Outputs: every command that writes checks, before any work, that a file's folder exists and is
writable (an output folder, such as a dataset's or a report's, is made with its missing parents, as
mkdir -p, where the nearest existing one is writable), that a file's name ends as it should (.npz,
.mcap, .bin, .png), and that it replaces nothing: an existing file (a dataset's recordings of the
same names, a certificate pair of the same name), or a report folder that is not empty, needs
--force. Each failure is one line and exit 2."""


def build_parser() -> argparse.ArgumentParser:
    """The whole command line: every command of every group, each with its help, defaults and example."""
    parser = Parser(prog="tactiled", description="Tactile roughness sensing daemon and toolkit.\n\n" + OUTPUT_POLICY,
                    epilog="exit codes: 0 ok, 1 failure, 2 usage or bad input\n\nexample:\n  tactiled demo --headless --seconds 20")
    parser.add_argument("--version", action="version", version=f"tactiled {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help="what to do (each command has --help)")
    for group in (cmd_setup, cmd_files, cmd_simulate, cmd_live, cmd_learn):
        group.add_commands(sub)
    return parser


ONE_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """One BLAS (and OpenMP) thread: every matrix here is small, and more threads only add overhead (13x slower ELM fits
    measured). Libraries not loaded yet (numpy is imported by the command's handler) read :data:`ONE_THREAD_VARIABLES`
    when they load, unless the environment sets them; so OpenBLAS starts no second thread, which spun ~0.1 s of another
    core after each start-up, and a replay ran its BLAS calls on two threads (threadpoolctl, called before numpy was
    loaded, found no library to limit). Libraries already loaded (main called in a process that imported numpy) are
    limited with threadpoolctl."""
    for name in ONE_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    if "numpy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``tactiled`` with ``argv`` (default: the process's arguments); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = min(getattr(args, "log_level", logging.WARNING), logging.WARNING - 10 * min(args.verbose, 2))  # -v info, -vv debug
    logging.basicConfig(level=level, format="tactiled: %(levelname)s: %(message)s", stream=sys.stderr)
    handler: Handler = args.handler
    one_blas_thread()
    from tactiled.signals import sigterm_as_exit  # here, not at the top: --help stops in parse_args without it

    try:
        with sigterm_as_exit():  # a plain kill stops a command as Ctrl-C does: its worker processes too (run and record have their own)
            return handler(args)
    except TactiledError as exc:
        print(f"tactiled: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_FAIL
    except BrokenPipeError as exc:  # stdout closed early (| head): quiet; any other pipe (a worker pool's) is said
        if not reader_gone(sys.stdout.fileno()):
            print(f"tactiled: error: {exc}", file=sys.stderr)
        return EXIT_FAIL
    except OSError as exc:  # the machine refused (a full disk, a folder gone): one line, what was already written stays
        print(f"tactiled: error: {exc}", file=sys.stderr)
        return EXIT_FAIL
    except Exception as exc:
        client = sys.modules.get("tactiled_client.errors")  # loaded if it raised (importing it here would load ZeroMQ)
        if client is not None and isinstance(exc, client.ClientError):  # the client library's: a --curve certificate unread
            print(f"tactiled: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        raise


def reader_gone(fd: int) -> bool:
    """Whether ``fd`` is the write end of a pipe whose reader has closed it (``tactiled replay --json | head -1``)."""
    import select

    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def hold_hangup(argv: Sequence[str]) -> None:
    """For ``tactiled run``: ignore SIGHUP until the daemon installs its own handler (a reload of the model), so that one
    during start-up (the imports, the model's load: about a second) does not end the daemon unannounced (SIGHUP's default
    action, exit 129). From when the command line is read: the interpreter's own start and this module's imports (about
    0.15 s) still end it, as they do any Python program. Other commands keep the default: a closed terminal ends them."""
    command = next((a for a in argv if not a.startswith("-")), None)
    if command == "run":
        signal.signal(signal.SIGHUP, signal.SIG_IGN)


def run() -> NoReturn:
    """The ``tactiled`` process (the console script, ``python -m tactiled``): :func:`main` of its arguments, then exit with the code.

    The process ends there, so every object it made is first frozen out of the cycle collector (:func:`gc.freeze`): the
    interpreter's collections at exit would traverse them all (numpy's, PyWavelets', tactiled's) for nothing. Exit handlers,
    flushing and module teardown run as before; only cyclic garbage is left to the operating system. After a replay of 5
    minutes the exit took 30 ms, frozen 9 ms (2026-11-26, the 2-core Xeon VM)."""
    hold_hangup(sys.argv[1:])
    code = main()
    gc.freeze()
    sys.exit(code)


__all__ = ["build_parser", "main", "run", "subcommands"]

if __name__ == "__main__":  # pragma: no cover
    run()
