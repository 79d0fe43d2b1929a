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


def _frames(kind: str, seq: int, sent_unix: float, sensor: str = "s0", **fields: object) -> list[bytes]:
    body = {"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": sensor, "type": kind, "time_unix": sent_unix, **fields}
    return [f"{kind}/{sensor}".encode(), msgpack.packb(body, use_bin_type=True)]


def _label(seq: int, sent_unix: float, label: str, sensor: str = "s0") -> list[bytes]:
    return _frames("roughness", seq, sent_unix, sensor, label=label, confidence=0.9, final=True, slide_id=seq)


def _status(seq: int, sent_unix: float, sensor: str = "s0") -> list[bytes]:
    return _frames("status", seq, sent_unix, sensor, state="idle")


@pytest.mark.parametrize("clock_ahead_s", [0.0, 1000.0, -1000.0])
def test_latest_counts_the_time_a_label_waited_in_the_queue_whatever_the_daemons_clock(clock_ahead_s: float, tmp_path: Path) -> None:
    """Statuses sent now, then a label sent 80 s ago (it waited in the queue while the controller was busy): ``latest(2)``
    is None; a label sent now is given. The same with the daemon's wall clock 1000 s ahead of the controller's or behind
    it: the library measures the wait against the quickest message, not against its own clock."""
    endpoint = f"ipc://{tmp_path}/pub"
    with xpub_socket(endpoint) as pub, BlockingSubscriber(endpoint, timeout=20) as sub:
        assert pub.poll(20_000), "no subscription came"
        pub.recv()
        for k in range(2):
            pub.send_multipart(_status(k, time.time() + clock_ahead_s))
        pub.send_multipart(_label(0, time.time() + clock_ahead_s - 80.0, "Ra1.00"))
        assert [sub.receive().type for _ in range(3)] == ["status", "status", "roughness"]
        assert sub.latest(max_age_s=2.0) is None, "a label 80 s old was given as fresh"
        assert sub.latest(max_age_s=100.0) is not None
        pub.send_multipart(_label(1, time.time() + clock_ahead_s, "Ra1.18"))
        fresh = sub.receive()
        assert isinstance(fresh, Roughness) and sub.latest(max_age_s=2.0) is fresh


def test_each_daemons_clock_is_its_own_and_one_wrong_stamp_does_not_stop_the_labels(tmp_path: Path) -> None:
    """One subscriber, two daemons: one's clock 10 s ahead, the other's right. Labels of the second, sent now, are fresh
    (one least lag for both made every one of them look 10 s late). Then one status stamped 1e300 (a clock wrong for a
    moment): the labels after it are still fresh (it was the least lag for 300 s, and every label looked stale)."""
    endpoint = f"ipc://{tmp_path}/pub"
    with xpub_socket(endpoint) as pub, BlockingSubscriber(endpoint, timeout=20) as sub:
        assert pub.poll(20_000), "no subscription came"
        pub.recv()
        for k in range(2):
            pub.send_multipart(_status(k, time.time() + 10.0, "ahead"))
            pub.send_multipart(_status(k, time.time(), "right"))
        pub.send_multipart(_label(0, time.time(), "Ra1.00", "right"))
        assert [sub.receive().sensor for _ in range(5)] == ["ahead", "right", "ahead", "right", "right"]
        assert sub.latest(max_age_s=2.0) is not None, "a label sent now was taken for 10 s old"
        pub.send_multipart(_status(2, 1e300, "right"))
        pub.send_multipart(_status(3, time.time(), "right"))
        pub.send_multipart(_label(1, time.time(), "Ra1.18", "right"))
        assert [sub.receive().type for _ in range(3)] == ["status", "status", "roughness"]
        assert sub.latest(max_age_s=2.0) is not None, "one wrong stamp made the labels after it look stale"


def _log(path: Path, entries: list[tuple[list[bytes], float, float]]) -> Path:
    with LogWriter(path) as log:
        for frames, mono, unix in entries:
            log.write(frames, mono, unix)
    return path


def test_a_replayed_session_ages_a_label_by_its_recorded_wait(tmp_path: Path) -> None:
    """A session log where a label arrived 30 s after it was sent (the recorder's subscriber was behind), after statuses
    that arrived at once: in the replay, ``latest(2)`` is None after it, and the fresh label after it is given."""
    path = _log(tmp_path / "s.tlog", [(_status(0, 1.7e9), 100.0, 1.7e9 + 0.001), (_status(1, 1.7e9 + 0.5), 100.5, 1.7e9 + 0.501),
                                      (_label(0, 1.7e9 - 29.0, "Ra1.00"), 101.0, 1.7e9 + 1.0),
                                      (_label(1, 1.7e9 + 2.0, "Ra1.18"), 102.0, 1.7e9 + 2.001)])
    with BlockingReplay(path, speed=None) as rep:
        assert [rep.receive().type for _ in range(2)] == ["status", "status"]
        assert isinstance(rep.receive(), Roughness) and rep.latest(max_age_s=2.0) is None
        fresh = rep.receive()
        assert isinstance(fresh, Roughness) and rep.latest(max_age_s=2.0) is fresh


def test_a_paced_replay_ages_a_label_the_controller_took_late(tmp_path: Path) -> None:
    """At speed 1000, a controller busy for 0.1 s of wall time (100 s of recorded time) then takes a label that was due long
    before: ``latest(2)`` is None, as live (its age began when it was taken, so it looked fresh)."""
    path = _log(tmp_path / "s.tlog", [(_status(0, 1.7e9), 100.0, 1.7e9), (_status(1, 1.7e9 + 0.5), 100.5, 1.7e9 + 0.5),
                                      (_label(0, 1.7e9 + 1.0, "Ra1.00"), 101.0, 1.7e9 + 1.0)])
    with BlockingReplay(path, speed=1000.0) as rep:
        assert rep.receive().type == "status"
        assert rep._origin is not None  # the controller busy for 0.1 s of wall time: the replay's clock started that much earlier
        rep._origin = (rep._origin[0], rep._origin[1] - 0.1)
        assert [rep.receive().type for _ in range(2)] == ["status", "roughness"]
        assert rep.latest(max_age_s=2.0) is None


def test_a_session_published_again_is_stamped_when_sent(tmp_path: Path) -> None:
    """``replay --publish`` stamps each message's ``time_unix`` when it sends it, as the daemon does: a label published
    from a log of 2023 (or slowed down) is fresh to its subscriber, where it kept the recorded stamp and looked stale."""
    from tactiled_client.replay import publish

    path = _log(tmp_path / "s.tlog", [(_status(k, 1.7e9 + k), 100.0 + k, 1.7e9 + k) for k in range(3)]
                + [(_label(0, 1.7e9 + 3, "Ra1.00"), 103.0, 1.7e9 + 3)])
    endpoint = f"ipc://{tmp_path}/pub"
    with BlockingSubscriber(endpoint, timeout=20) as sub:
        before = time.time()
        assert publish(path, endpoint, speed=None, wait_subscriber_s=20) == 4
        got = [sub.receive() for _ in range(4)]
    assert all(m.time_unix >= before for m in got) and sub.latest(max_age_s=2.0) is got[-1]


def test_the_client_package_says_it_is_typed() -> None:
    """``py.typed`` ships in the installed client distribution, so a controller's mypy reads its annotations (PEP 561)."""
    from importlib.metadata import files

    assert "tactiled_client/py.typed" in {str(f) for f in files("tactiled-client") or []}


def test_the_example_controller_says_a_damaged_log_in_one_line(tmp_path: Path) -> None:
    """``example_controller.py --replay`` of a log with a flipped byte: one line naming the file, exit 2, no traceback."""
    path = tmp_path / "s.tlog"
    with LogWriter(path) as log:
        for i in range(20):
            log.write(_status(i, 1.7e9 + 0.01 * i), 100.0 + 0.01 * i, 1.7e9 + 0.01 * i)  # replayed at speed 1: 0.2 s
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, str(REPO / "clients" / "example_controller.py"), "--replay", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1 and str(path) in proc.stderr
