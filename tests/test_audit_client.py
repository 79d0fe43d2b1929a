"""The client library's answers to an outside audit: a session log holding a newer schema's message replays, a ROS 2 bag
is named as one, a seq no daemon sends is refused, and the recorder counts a message of the wrong number of frames."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import msgpack
import pytest
import zmq
from tactiled_client import BlockingReplay, BlockingSubscriber, LogError, schema
from tactiled_client.log import LogWriter
from tactiled_client.subscriber import _Tracker

from tests.conftest import recorder_thread, xpub_socket


def _body(seq: int, v: int = schema.SCHEMA_VERSION, **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": v, "seq": seq, "sensor": "s0", "type": "status", "state": "idle", **fields}, use_bin_type=True)
    return out


def test_a_session_log_holding_a_newer_schema_message_replays_every_message(tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A ``"v": 9`` message stopped ``replay --json`` and BlockingReplay with a LogError, losing every message after it;
    the live subscriber takes it (its new field in ``extra``), and so must the log reader."""
    from tactiled_client.__main__ import main

    path = tmp_path / "x.tlog"
    with LogWriter(path) as log:
        for seq, body in enumerate([_body(0), _body(1), _body(2, v=schema.SCHEMA_VERSION + 1, novel=7), _body(3)]):
            log.write([b"status/s0", body], 100.0 + seq / 10, 1e9 + seq / 10)
    assert main(["replay", str(path), "--json"]) == 0
    out = capsys.readouterr()
    lines = [json.loads(line) for line in out.out.splitlines()]
    assert [line["seq"] for line in lines] == [0, 1, 2, 3] and lines[2]["novel"] == 7, out.err
    with BlockingReplay(path, speed=None) as rep:
        msgs = list(rep)
    assert [m.seq for m in msgs] == [0, 1, 2, 3] and msgs[2].extra == {"novel": 7}


def test_a_ros2_bag_is_refused_in_one_line_saying_what_it_is(tmp_path: Path) -> None:
    """tactiled's ROS 2 bag (CDR roughness messages) failed with ``not JSON: 'utf-16-be' codec can't decode``."""
    from mcap.writer import Writer

    path = tmp_path / "bag.mcap"
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start("ros2", "test")
        sid = writer.register_schema("tactiled_msgs/msg/Roughness", "ros2msg", b"float64 ra")
        chan = writer.register_channel("/tactiled/s0/roughness", "cdr", sid)
        writer.add_message(chan, log_time=1, publish_time=1, data=b"\x00\x01\x00\x00" + bytes(8), sequence=0)
        writer.finish()
    with pytest.raises(LogError) as err, BlockingReplay(path, speed=None) as rep:
        list(rep)
    text = str(err.value)
    assert "\n" not in text and "ROS 2 bag" in text and "JSON MCAP export" in text and "utf-16" not in text, text


@pytest.mark.parametrize("seq", [2**64 - 1, 2**63, -1])
def test_a_seq_no_daemon_sends_is_refused_and_gap_detection_goes_on(seq: int) -> None:
    """A stray ``seq`` 2**64-1 reported missed=18446744073709551614, then every genuine message looked like a restart."""
    tracker = _Tracker()
    assert tracker.accept([b"status/s0", _body(0)]) is not None
    assert tracker.accept([b"status/s0", _body(seq)]) is None
    assert tracker.malformed == 1 and "seq" in (tracker.last_malformed or "")
    msg = tracker.accept([b"status/s0", _body(3)])
    assert msg is not None and msg.missed == 2 and tracker.missed["status/s0"] == 2
    assert tracker.accept([b"status/s0", _body(2**63 - 1)]) is not None  # the largest seq is still one


def test_the_live_subscriber_skips_a_seq_no_daemon_sends(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/pub"
    with xpub_socket(endpoint) as pub, BlockingSubscriber(endpoint, topics=["status"]) as sub:
        assert pub.poll(20_000)
        pub.recv()
        for seq in (0, 2**64 - 1, 1):
            pub.send_multipart([b"status/s0", _body(seq)])
        assert [(m.seq, m.missed) for m in (sub.receive(timeout=20), sub.receive(timeout=20))] == [(0, 0), (1, 0)]


def test_the_recorder_counts_a_message_that_is_not_two_frames(tmp_path: Path) -> None:
    """A three-frame message was neither recorded nor counted among the messages not recorded."""

    endpoint = f"ipc://{tmp_path}/pub"
    pub: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind(endpoint)
    stop, done = threading.Event(), threading.Event()
    refused: list[str] = []

    def on_message(n: int) -> None:
        if n == 1:
            done.set()

    thread = recorder_thread(endpoint, tmp_path / "s.tlog", stop, on_message, refused)
    try:
        assert pub.poll(20_000)
        pub.recv()
        pub.send_multipart([b"status/s0", _body(0), b"extra"])
        pub.send_multipart([b"status/s0", _body(1)])  # after it on the same socket: once recorded, the first was seen
        assert done.wait(20)
    finally:
        stop.set()
        thread.join(20)
        pub.close(linger=0)
    assert not thread.is_alive() and refused == ["status/s0: 3 frames, not 2"]
