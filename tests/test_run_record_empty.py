"""``tactiled run --record OUT.npz`` on a port that never sends a frame: no empty recording left, one line saying so.

A recording with samples is still written at SIGTERM: tests/test_record.py::test_run_record_streams_to_the_journal_and_sigterm_saves.
"""

from __future__ import annotations

import os
from pathlib import Path

from tactiled_client import BlockingSubscriber, Status

from tests.conftest import daemon_process, wait_for


def test_run_record_of_no_sample_writes_no_file_and_says_so(tmp_path: Path) -> None:
    master, slave = os.openpty()  # a real pty whose other end never writes a byte
    try:
        out, endpoint = tmp_path / "out.npz", f"ipc://{tmp_path}/pub"
        with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as sub, \
                daemon_process(os.ttyname(slave), endpoint, "--no-model", "--record", str(out)) as proc:
            wait_for(lambda: isinstance(sub.receive(), Status), timeout=30, what="the daemon's first status")  # running: SIGTERM is caught
            assert (tmp_path / "out.npz.journal").exists()  # the recorder was streaming to its journal
            proc.terminate()
            _, err = proc.communicate(timeout=30)
    finally:
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, err
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("out.npz")] == []  # neither out.npz nor its journal
    said = [line for line in err.splitlines() if "nothing was recorded" in line]
    assert len(said) == 1 and said[0].endswith(f"nothing was recorded (no sample received), so {out} was not written"), err
    assert "saved" not in err, err
