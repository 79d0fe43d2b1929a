"""The client recorder against an outside audit: a write the machine refuses (a file-size limit) is one line and exit 1, the
messages before it kept readable; a device or a FIFO at the output path is refused before recording (it wrote /dev/null
then failed in fsync, and hung in open() on a FIFO); and the client's help says what docs/cli.md shows of it."""

from __future__ import annotations

import os
import re
import resource
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from tactiled_client.log import LogReader

from tests.conftest import REPO, status_publisher

LIMIT = 50_000  # bytes the recorder may write (ulimit -f 50 is 51200)


def _file_size_limit() -> None:
    """In the recorder's process before it starts: at most :data:`LIMIT` bytes per file, SIGXFSZ ignored (as Python does,
    and the auditor's EFBIG shows), so a write past it fails with EFBIG instead of killing the process."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def _record(*args: str, timeout: float = 30.0, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tactiled_client", "record", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, **kw)  # type: ignore[call-overload, no-any-return]


def test_a_file_size_limit_ends_the_recording_in_one_line_exit_1_every_message_before_it_readable(tmp_path: Path) -> None:
    """It ended in a traceback from log.py (OSError: [Errno 27] File too large), the file ending in a torn record."""
    endpoint = f"ipc://{tmp_path}/pub"
    out = tmp_path / "cr.tlog"
    with status_publisher(endpoint, every_s=0.01, payload=4000):
        res = _record("--seconds", "60", endpoint, str(out), "--force", preexec_fn=_file_size_limit)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert lines[0].startswith(f"tactiled_client: {out}: File too large: recording stopped after "), lines[0]
    kept = int(re.search(r"after (\d+) messages", lines[0]).group(1))  # type: ignore[union-attr]
    reader = LogReader(out)
    entries = list(reader)
    assert kept > 0 and len(entries) == kept and reader.truncated is None  # cut back to its last whole record
    assert all(e.topic == "status/s0" for e in entries) and out.stat().st_size <= LIMIT


def test_a_device_at_the_output_path_is_refused_before_recording(tmp_path: Path) -> None:
    """A symbolic link to /dev/null with --force: it recorded for --seconds, then a traceback from os.fsync (EINVAL)."""
    out = tmp_path / "out.tlog"
    out.symlink_to(os.devnull)
    res = _record("--seconds", "2", f"ipc://{tmp_path}/nobody", str(out), "--force", timeout=20)
    assert res.returncode == 2, res.stderr
    assert res.stderr == f"tactiled_client: {out}: not a regular file (a device or FIFO is never written)\n"


def test_a_fifo_at_the_output_path_is_refused_not_waited_on(tmp_path: Path) -> None:
    """A FIFO with --force: open() waited for a reader for ever, whatever --seconds said."""
    out = tmp_path / "out.tlog"
    os.mkfifo(out)
    try:
        res = _record("--seconds", "1", f"ipc://{tmp_path}/nobody", str(out), "--force", timeout=20)
    except subprocess.TimeoutExpired:
        pytest.fail("record still waiting on the FIFO after 20 s")
    assert res.returncode == 2, res.stderr
    assert res.stderr == f"tactiled_client: {out}: not a regular file (a device or FIFO is never written)\n"
    assert stat.S_ISFIFO(out.stat().st_mode)  # left as it was


def test_the_client_help_says_what_docs_cli_md_shows_of_it() -> None:
    """docs/cli.md showed replay --wait-subscriber S ... (default: 0.0), which the command's own --help did not say."""
    doc = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    env = {**os.environ, "COLUMNS": "102"}  # argparse wraps at COLUMNS - 2: docs/cli.md's width, 100
    for command in ("record", "replay", "control"):
        res = subprocess.run([sys.executable, "-m", "tactiled_client", command, "--help"], cwd=REPO, capture_output=True, text=True,
                             timeout=30, env=env)
        assert res.returncode == 0, res.stderr
        assert f"```\n{res.stdout.rstrip()}\n```" in doc, f"docs/cli.md differs from python -m tactiled_client {command} --help"
