"""The one check every file tactiled reads goes through first: a regular file below a size limit.

A device (``/dev/zero``) would be read without end and a FIFO would block the reader; a folder is no file. Recordings,
captures, journals, models, feature files and keys are all checked here before they are opened, by their size as the
file system states it, so nothing is read from a path that fails. The reasons are phrases to follow the path
(``x.npz: not a regular file (...)``); each caller raises them as its own error class.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

MISSING = "does not exist"
NOT_REGULAR = "not a regular file (a device, FIFO or folder is never read)"


def file_problem(path: str | Path, max_bytes: int) -> str | None:
    """Why ``path`` is not a regular file of at most ``max_bytes`` bytes (:data:`MISSING`, :data:`NOT_REGULAR`, or its
    size against the limit), or None if it is one. Follows symbolic links; never opens the file."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return MISSING
    except OSError as exc:
        return exc.strerror or str(exc)
    except ValueError as exc:  # a path no file can have: a NUL character (a path from a control request, not argv)
        return f"not a path ({exc})"
    if not stat.S_ISREG(info.st_mode):
        return NOT_REGULAR
    if info.st_size > max_bytes:
        return f"{info.st_size} bytes, more than the {max_bytes} a file there may have"
    return None
