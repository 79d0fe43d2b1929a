"""The client library's answers to an audit: a recorder that stops, sensor filters that filter, timeouts everywhere and in
recorded time, one-line errors for bad key files and bad command lines, secret keys only the owner reads, quiet pipes."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import zmq
from tactiled_client import schema

from tests.conftest import REPO


def _body(kind: str, seq: int, sensor: str = "s0", **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": sensor, "type": kind, **fields}, use_bin_type=True)
    return out


@contextlib.contextmanager
def steady_publisher(endpoint: str, every_s: float = 0.02) -> Iterator[threading.Event]:
    """An XPUB on ``endpoint`` that, once a subscriber has subscribed (the event it yields is set then), sends a status
    message every ``every_s`` without a pause, until the block ends: the busy topic that never leaves a quiet moment."""
    subscribed, stop = threading.Event(), threading.Event()
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(endpoint)

    def run() -> None:
        seq = 0
        while not stop.is_set():
            if not subscribed.is_set():
                if sock.poll(50):
                    sock.recv()
                    subscribed.set()
                continue
            sock.send_multipart([b"status/s0", _body("status", seq, state="idle")])
            seq += 1
            stop.wait(every_s)  # the publisher's pace, not a synchronisation

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield subscribed
    finally:
        stop.set()
        thread.join(10)
        sock.close(linger=0)


def test_record_ends_on_time_and_on_a_signal_against_a_publisher_that_never_pauses(tmp_path: Path) -> None:
    """It drained until 200 ms of quiet: against a message every 100 ms ``--seconds 1`` ran for 410 s and ignored SIGTERM."""
    from tactiled_client.record import record

    endpoint = f"ipc://{tmp_path}/steady"
    done: list[int] = []
    with steady_publisher(endpoint):
        thread = threading.Thread(target=lambda: done.append(record(endpoint, tmp_path / "a.tlog", seconds=0.5)), daemon=True)
        start = time.monotonic()
        thread.start()
        thread.join(5.0)
        assert not thread.is_alive(), "record(seconds=0.5) still running after 5 s"
    assert time.monotonic() - start < 5.0 and done and done[0] > 0
    with steady_publisher(endpoint.replace("steady", "steady2")) as subscribed:
        proc = subprocess.Popen([sys.executable, "-m", "tactiled_client", "record", endpoint.replace("steady", "steady2"),
                                 str(tmp_path / "b.tlog")], cwd=REPO, stderr=subprocess.PIPE, text=True)
        try:
            assert subscribed.wait(30), "the recorder never subscribed"  # its signal handlers are set before it subscribes
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=5)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert proc.returncode == 0 and "b.tlog:" in err and "messages" in err, err
