"""A controller's view of the client library (an outside audit, nineteenth session): ``latest()`` counts the time a
label waited in the queue, the package carries its types, and the example controller says a damaged log in one line.

Real ZeroMQ sockets on ipc, real files and processes.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
from tactiled_client import BlockingReplay, BlockingSubscriber, Roughness, schema
from tactiled_client.log import LogWriter

from tests.conftest import REPO, xpub_socket


def _frames(kind: str, seq: int, sent_unix: float, **fields: object) -> list[bytes]:
    body = {"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": "s0", "type": kind, "time_unix": sent_unix, **fields}
    return [f"{kind}/s0".encode(), msgpack.packb(body, use_bin_type=True)]


def _label(seq: int, sent_unix: float, label: str) -> list[bytes]:
    return _frames("roughness", seq, sent_unix, label=label, confidence=0.9, final=True, slide_id=seq)


@pytest.mark.parametrize("clock_ahead_s", [0.0, 1000.0, -1000.0])
def test_latest_counts_the_time_a_label_waited_in_the_queue_whatever_the_daemons_clock(clock_ahead_s: float, tmp_path: Path) -> None:
    """Statuses sent now, then a label sent 80 s ago (it waited in the queue while the controller was busy): ``latest(2)``
    is None; a label sent now is given. The same with the daemon's wall clock 1000 s ahead of the controller's or behind
    it: the library measures the wait against the quickest message, not against its own clock."""
    endpoint = f"ipc://{tmp_path}/pub"
    with xpub_socket(endpoint) as pub, BlockingSubscriber(endpoint, timeout=20) as sub:
        assert pub.poll(20_000), "no subscription came"
        pub.recv()
        now = time.time() + clock_ahead_s
        pub.send_multipart(_frames("status", 0, now, state="idle"))
        pub.send_multipart(_label(0, now - 80.0, "Ra1.00"))
        assert sub.receive().type == "status" and isinstance(sub.receive(), Roughness)
        assert sub.latest(max_age_s=2.0) is None, "a label 80 s old was given as fresh"
        assert sub.latest(max_age_s=100.0) is not None
        pub.send_multipart(_label(1, time.time() + clock_ahead_s, "Ra1.18"))
        fresh = sub.receive()
        assert isinstance(fresh, Roughness) and sub.latest(max_age_s=2.0) is fresh


def test_a_replayed_session_ages_a_label_by_its_recorded_wait(tmp_path: Path) -> None:
    """A session log where a label arrived 30 s after it was sent (the recorder's subscriber was behind), between statuses
    that arrived at once: in the replay, ``latest(2)`` is None after it, and the fresh label after it is given."""
    path = tmp_path / "s.tlog"
    with LogWriter(path) as log:
        log.write(_frames("status", 0, 1.7e9, state="idle"), 100.0, 1.7e9 + 0.001)
        log.write(_label(0, 1.7e9 - 29.0, "Ra1.00"), 101.0, 1.7e9 + 1.0)
        log.write(_label(1, 1.7e9 + 2.0, "Ra1.18"), 102.0, 1.7e9 + 2.001)
    with BlockingReplay(path, speed=None) as rep:
        assert rep.receive().type == "status"
        assert isinstance(rep.receive(), Roughness) and rep.latest(max_age_s=2.0) is None
        fresh = rep.receive()
        assert isinstance(fresh, Roughness) and rep.latest(max_age_s=2.0) is fresh


def test_the_client_package_says_it_is_typed() -> None:
    """``py.typed`` ships in the installed client distribution, so a controller's mypy reads its annotations (PEP 561)."""
    from importlib.metadata import files

    assert "tactiled_client/py.typed" in {str(f) for f in files("tactiled-client") or []}


def test_the_example_controller_says_a_damaged_log_in_one_line(tmp_path: Path) -> None:
    """``example_controller.py --replay`` of a log with a flipped byte: one line naming the file, exit 2, no traceback."""
    path = tmp_path / "s.tlog"
    with LogWriter(path) as log:
        for i in range(20):
            log.write(_frames("status", i, 1.7e9 + i, state="idle"), 100.0 + i, 1.7e9 + i)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, str(REPO / "clients" / "example_controller.py"), "--replay", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1 and str(path) in proc.stderr
