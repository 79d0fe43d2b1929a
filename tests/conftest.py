"""Shared test helpers: waiting on events with a timeout, running the CLI as a process."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def wait_for(predicate: Callable[[], object], timeout: float = 20.0, what: str = "condition") -> object:
    """Call ``predicate`` until it returns something truthy; fail after ``timeout`` seconds.

    ``predicate`` must itself wait for the next event (e.g. a subscriber's ``receive`` with a
    timeout), so this loop never sleeps or spins.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def tactiled_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "tactiled", *args]


def run_cli(*args: str, timeout: float = 120.0, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(tactiled_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=REPO, **kw)  # type: ignore[call-overload, no-any-return]


@pytest.fixture
def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONUNBUFFERED"] = "1"
    return e
