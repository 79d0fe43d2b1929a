"""Outputs checked before any work: one policy for every command that writes a file or a folder.

The folder must exist and be writable; a file's name must end as it should (``.npz``, ``.mcap``, ``.bin``, ``.png``);
nothing is replaced without ``force``: an existing file, or a folder of outputs that is not empty. A device or a FIFO
is never written. Each failure is an :class:`~tactiled.errors.OutputError` of one line naming the path.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from tactiled.errors import OutputError


def check_output(out: str | Path, force: bool, suffixes: tuple[str, ...] = (), inputs: Iterable[str | Path] = ()) -> None:
    """Raise :class:`OutputError` naming ``out`` unless a file can be written there: its folder exists and is writable,
    its name ends in one of ``suffixes`` (if given), it is none of the command's ``inputs`` (even with ``force``: a
    recording read would be replaced by what was made of it), and, without ``force``, no file is there already.

    Every command that writes a file calls this before any work (docs/cli.md: the output policy).
    """
    out = Path(out)
    folder = out.parent
    if any(Path(i).resolve() == out.resolve() for i in inputs):
        raise OutputError(f"{out}: is one of the files it reads; write it elsewhere")
    if not folder.exists():
        raise OutputError(f"{out}: folder {folder} does not exist")
    if not folder.is_dir():
        raise OutputError(f"{out}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: folder {folder} is not writable")
    if out.is_dir():
        raise OutputError(f"{out}: is a folder")
    if out.exists() and not out.is_file():
        raise OutputError(f"{out}: not a regular file (a device or FIFO is never written)")
    if suffixes and out.suffix.lower() not in suffixes:
        raise OutputError(f"{out}: must end in {' or '.join(suffixes)}")
    if out.exists() and not force:
        raise OutputError(f"{out}: exists (--force overwrites it)")


def check_folder(out: str | Path, force: bool) -> None:
    """Raise :class:`OutputError` naming ``out`` unless a folder of outputs can be made there (with its missing parents,
    as ``mkdir -p``): the nearest existing ancestor is a writable folder, nothing but a folder is there, and, without
    ``force``, no non-empty folder is there already."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder")
    if out.is_dir():
        if not os.access(out, os.W_OK | os.X_OK):
            raise OutputError(f"{out}: folder is not writable")
        if not force and any(out.iterdir()):
            raise OutputError(f"{out}: folder exists and is not empty (--force writes into it, replacing files of the same names)")
        return
    parent = out.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    check_output(parent / out.name, force=True)  # the nearest existing ancestor: a folder, writable
