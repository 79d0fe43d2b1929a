"""docs/cli.md, generated from the parser: ``python -m tactiled.cli.clidoc > docs/cli.md``.

:func:`cli_markdown` renders every command's ``--help`` at a fixed width, so the page is the
same on every terminal; tests/test_cli.py fails when docs/cli.md differs from it.
"""

from __future__ import annotations

import argparse
import functools
import sys

from tactiled.cli.common import HelpFormatter, subcommands
from tactiled.cli.main import build_parser

WIDTH = 100
REGENERATE = "python -m tactiled.cli.clidoc > docs/cli.md"


def _help(parser: argparse.ArgumentParser, width: int) -> str:
    """``parser.format_help()`` at ``width`` columns, whatever the terminal."""
    saved = parser.formatter_class
    parser.formatter_class = functools.partial(HelpFormatter, width=width)  # type: ignore[assignment]
    try:
        return parser.format_help()
    finally:
        parser.formatter_class = saved


def cli_markdown(parser: argparse.ArgumentParser, width: int = WIDTH) -> str:
    """The command line reference in Markdown: an index, then the help of every (sub)command of ``parser``."""
    commands = subcommands(parser)
    lines = ["# Command line reference", "",
             f"The output of `{parser.prog} <command> --help` for every command, generated from the parser by `{REGENERATE}`",
             "(a test keeps this page equal to it). Exit codes: 0 ok, 1 failure, 2 usage or bad input (config, recording, model,",
             "device path).", ""]
    for words, p in commands.items():
        if words and not any(isinstance(a, argparse._SubParsersAction) for a in p._actions):
            title = f"{parser.prog} {words}"
            lines.append(f"- [`{title}`](#{title.replace(' ', '-')}): {p.description}")
    for words, p in commands.items():
        lines += ["", f"## {parser.prog} {words}".rstrip(), "", "```", _help(p, width).rstrip(), "```"]
    return "\n".join(lines) + "\n"


def reference(width: int = WIDTH) -> str:
    """docs/cli.md: :func:`cli_markdown` of ``tactiled``, then the help of the client library's ``python -m tactiled_client``."""
    from tactiled_client.__main__ import build_parser as client_parser

    client = client_parser()
    lines = ["", "# The client library's command line", "",
             f"`{client.prog}` (installed with the client library alone: `pip install ./clients`) records and replays sessions",
             "without the daemon and sends control requests to a running one.", ""]
    for words, p in subcommands(client).items():
        lines += ["", f"## {client.prog} {words}".rstrip(), "", "```", _help(p, width).rstrip(), "```"]
    return cli_markdown(build_parser(), width) + "\n".join(lines) + "\n"


def main() -> int:
    """Write docs/cli.md's text to stdout; exit code 0."""
    sys.stdout.write(reference())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
