"""Where a bench keeps the recordings and streams it makes: the folder ``--out`` names (kept), or a temporary one
removed when the bench's process ends (on an exception too; only a killed process leaves it)."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path


def scratch(out: str | None, prefix: str) -> Path:
    """``out`` (created if missing, kept), or a new temporary folder named ``prefix...`` removed at exit."""
    if out:
        path = Path(out)
        path.mkdir(parents=True, exist_ok=True)
        return path
    path = Path(tempfile.mkdtemp(prefix=prefix))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path
