"""The client library against hostile publishers and files (an outside audit): nothing it records is unreadable, and
nothing it reads crashes it. An oversize or non-map message is not recorded, counted and said, and recording goes on
(also after libzmq drops the publisher for a frame over MAXMSGSIZE); msgpack extension values print; receive times that
are no clock readings and wrongly typed ``tactiled replay --json`` fields are one line naming the byte or line, exit 2."""

from __future__ import annotations

import asyncio
import base64
import json
import signal
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import msgpack
import pytest
import zmq
from tactiled_client import BlockingReplay, LogError, Replay, schema
from tactiled_client.errors import RecordRefused
from tactiled_client.log import HEADER, MAX_RECORD, RECORD, LogReader, LogWriter

from tests.conftest import REPO, recorder_thread

T = TypeVar("T")


def _body(seq: int, **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": "s0", "type": "status", **fields}, use_bin_type=True)
    return out


def _padded(seq: int, size: int) -> bytes:
    """A status body of exactly ``size`` bytes (a ``pad`` field fills it)."""
    pad = size - len(_body(seq, pad=b"x" * 70_000))  # bin 32 header either way
    out = _body(seq, pad=b"x" * (70_000 + pad))
    assert len(out) == size
    return out


def _resubscribed(xpub: zmq.Socket[bytes], timeout: float = 20.0) -> None:
    """Wait until the subscriber's next subscription reaches ``xpub`` (after its connection was dropped and made again)."""
    deadline = time.monotonic() + timeout
    while True:
        left = int((deadline - time.monotonic()) * 1000)
        assert left > 0 and xpub.poll(left), "the recorder never subscribed again"
        if xpub.recv()[:1] == b"\x01":
            return


def test_the_recorder_writes_no_record_its_reader_refuses_and_records_on(tmp_path: Path) -> None:
    """A 70 MiB message was written as a 73 MB record the reader refuses ("more than the 67108864 a record may hold"):
    ``replay --json`` stopped there with exit 2 and every message after it was lost to replay. A body that is not msgpack
    stopped the replay alike. Now neither is written, both are counted in the summary, and after libzmq drops the
    publisher for the frame over MAXMSGSIZE the recorder connects again and records what comes next."""
    endpoint = f"ipc://{tmp_path}/pub"
    xpub: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    xpub.setsockopt(zmq.LINGER, 0)
    xpub.bind(endpoint)
    out = tmp_path / "s.tlog"
    proc = subprocess.Popen([sys.executable, "-m", "tactiled_client", "record", endpoint, str(out)], cwd=REPO, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert xpub.poll(30_000), "the recorder never subscribed"
        xpub.recv()
        xpub.send_multipart([b"status/s0", _body(0)])
        xpub.send_multipart([b"status/s0", b"\xc1\xc1"])  # not msgpack: the reader refuses the body
        xpub.send_multipart([b"status/s0", _padded(1, MAX_RECORD - 10)])  # a frame libzmq takes, a record over the limit
        xpub.send_multipart([b"status/s0", _body(2)])
        xpub.send_multipart([b"status/s0", _body(3, pad=b"x" * (70 << 20))])  # the audit's: a frame over MAXMSGSIZE
        for seq in (4, 5, 6):
            xpub.send_multipart([b"status/s0", _body(seq)])  # behind it on the dropped connection: lost, and seq says so
        _resubscribed(xpub)
        for seq in (7, 8):
            xpub.send_multipart([b"status/s0", _body(seq)])
        proc.send_signal(signal.SIGTERM)  # what is in flight is still drained
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        xpub.close(linger=0)
    assert proc.returncode == 0 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"{out}: 4 messages; 3 not recorded (the last: {endpoint}: its connection was dropped for a message over "
                          f"{MAX_RECORD} bytes"), err
    assert out.stat().st_size < 1000
    res = subprocess.run([sys.executable, "-m", "tactiled_client", "replay", str(out), "--json"], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert res.returncode == 0 and res.stderr == "", res.stderr
    assert [json.loads(line)["seq"] for line in res.stdout.splitlines()] == [0, 2, 7, 8]


def test_the_recorder_does_not_redial_a_publisher_that_went_away(tmp_path: Path) -> None:
    """libzmq reconnects to a publisher that restarts by itself: that is no dropped connection to report."""

    endpoint = f"ipc://{tmp_path}/pub"
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    stop, second = threading.Event(), threading.Event()
    refused: list[str] = []
    counts: list[int] = []

    def on_message(n: int) -> None:
        counts.append(n)
        if n == 2:
            second.set()

    xpub: zmq.Socket[bytes] = ctx.socket(zmq.XPUB)
    xpub.setsockopt(zmq.LINGER, 0)
    xpub.bind(endpoint)
    thread = recorder_thread(endpoint, tmp_path / "s.tlog", stop, on_message, refused)
    try:
        assert xpub.poll(20_000)
        xpub.recv()
        xpub.send_multipart([b"status/s0", _body(0)])
        xpub.close(linger=0)  # the daemon restarts
        xpub = ctx.socket(zmq.XPUB)
        xpub.setsockopt(zmq.LINGER, 0)
        xpub.bind(endpoint)
        _resubscribed(xpub)
        xpub.send_multipart([b"status/s0", _body(0)])
        assert second.wait(20), f"recorded {counts}"
    finally:
        stop.set()
        thread.join(20)
        xpub.close(linger=0)
    assert not thread.is_alive() and refused == []


def test_a_log_writer_refuses_every_record_its_reader_would_refuse(tmp_path: Path) -> None:
    """LogWriter wrote any size, any body and any time; the reader then refused the file from that record on."""
    path = tmp_path / "s.tlog"
    bad = [([b"status/s0", _padded(1, MAX_RECORD)], 10.0, "a record of 67108898 bytes, more than the 67108864 a record may hold"),
           ([b"status/s0", b"\xc1"], 10.0, "message body is not msgpack"),
           ([b"status/s0", msgpack.packb([1, 2])], 10.0, "message body is not a map"),
           ([b"status/s0", _body(1)], float("inf"), "recv_mono inf is not a clock reading"),
           ([b"status/s0", _body(1)], float("nan"), "recv_mono nan is not a clock reading"),
           ([b"status/s0", _body(1)], 1e15, "recv_mono 1000000000000000.0 is not a clock reading"),
           ([b"status/s0", _body(1)], 5.0, "recv_mono goes back 5 s from the record before"),
           ([b"status/s0", _body(1)], 10.0 + 1e8, "recv_mono jumps 1e+08 s past the record before")]
    with LogWriter(path) as log:
        log.write([b"status/s0", _body(0)], 10.0, 1.7e9)
        for frames, t, what in bad:
            with pytest.raises(RecordRefused, match=what.replace("+", r"\+")) as info:
                log.write(frames, t, 1.7e9)
            assert info.value.reason.startswith("status/s0: ") and str(info.value) == f"{path}: {info.value.reason}"
        log.write([b"status/s0", _body(1)], 11.0, 1.7e9)
        log.write([b"status/s0", _body(2, v=schema.SCHEMA_VERSION + 1)], 12.0, 1.7e9)  # a newer daemon's: kept for a newer client
        assert log.count == 3
    reader = LogReader(path)
    assert [e.time_mono for e in reader] == [10.0, 11.0, 12.0]  # a newer schema's message is read, its new fields aside


def _log(path: Path, times: list[float]) -> list[int]:
    """A session log with one status message at each recorded time, written as a writer that checks nothing would (valid
    header, lengths and CRCs); the byte offset of each record."""
    data, at = bytearray(HEADER), []
    for seq, t in enumerate(times):
        payload = msgpack.packb([t, 1.7e9, "status/s0", _body(seq)], use_bin_type=True)
        at.append(len(data))
        data += RECORD.pack(len(payload), zlib.crc32(payload)) + payload
    path.write_bytes(bytes(data))
    return at


@pytest.mark.parametrize(("t", "what"), [(float("inf"), "recv_mono inf is not a clock reading"),
                                         (float("nan"), "recv_mono nan is not a clock reading"),
                                         (1e15, "recv_mono 1000000000000000.0 is not a clock reading"),
                                         (90.0, "recv_mono goes back 10 s from the record before"),
                                         (100.0 + 1e8, "recv_mono jumps 1e+08 s past the record before")])
def test_a_receive_time_that_is_no_clock_reading_is_one_line_naming_the_byte(t: float, what: str, tmp_path: Path,
                                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``recv_mono`` inf or 1e15 raised OverflowError out of time.sleep (replay --json --speed 1, --publish, BlockingReplay,
    Replay); one going back or jumping a lifetime was replayed as if it were a time. The message before it is replayed."""
    from tactiled_client.__main__ import main

    path = tmp_path / "s.tlog"
    at = _log(path, [100.0, t, 100.2])[1]
    line = f"{path}: byte {at}: {what}"

    def blocking() -> None:
        with BlockingReplay(path, speed=1.0) as rep:
            assert rep.receive().seq == 0
            rep.receive()

    async def run() -> None:
        async with Replay(path, speed=1.0) as sub:
            async for _ in sub:
                pass

    for replay in (blocking, lambda: asyncio.run(run())):
        with pytest.raises(LogError) as info:
            _within(replay)
        assert str(info.value).startswith(line), info.value
    for extra in (["--json", "--speed", "1"], ["--publish", f"ipc://{tmp_path}/pub"]):
        assert _within(lambda: main(["replay", str(path), *extra])) == 2  # noqa: B023 (run at once)
        out, err = capsys.readouterr()
        assert err.startswith(f"tactiled_client: {line}") and len(err.splitlines()) == 1, err
        assert len(out.splitlines()) == (1 if "--json" in extra else 0)


def _within(call: Callable[[], T], timeout: float = 20.0) -> T:
    """``call()``'s result (or its exception), failing if it is still running after ``timeout`` s: a replay that sleeps
    for a recorded year, as the unchecked code did, fails the test instead of hanging it (the thread is left asleep)."""
    values: list[T] = []
    errors: list[BaseException] = []

    def run() -> None:
        try:
            values.append(call())
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    assert values or errors, f"still running after {timeout} s"
    if errors:
        raise errors[0]
    return values[0]


def _records(path: Path, bodies: list[bytes]) -> list[int]:
    """A session log of these status bodies, 0.1 s apart; the byte offset of each record."""
    data, at = bytearray(HEADER), []
    for i, body in enumerate(bodies):
        payload = msgpack.packb([100.0 + 0.1 * i, 1.7e9, "status/s0", body], use_bin_type=True)
        at.append(len(data))
        data += RECORD.pack(len(payload), zlib.crc32(payload)) + payload
    path.write_bytes(bytes(data))
    return at


def test_replay_json_prints_msgpack_extension_values(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``msgpack.ExtType(5, b"abc")`` or a ``msgpack.Timestamp`` in a body: a TypeError traceback (not JSON serializable),
    exit 1. A subscriber delivers such a message (its head is right), so the replay prints it: ``{"ext": code, "data"}``."""
    from tactiled_client.__main__ import main

    path = tmp_path / "s.tlog"
    stamp = msgpack.Timestamp(1_700_000_000, 5)
    _records(path, [_body(0, x=msgpack.ExtType(5, b"abc")), _body(1, when=stamp), _body(2, deep={"k": [msgpack.ExtType(7, b"")]})])
    assert main(["replay", str(path), "--json"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines[0]["x"] == {"ext": 5, "data": "YWJj"}
    assert lines[1]["when"]["ext"] == -1 and msgpack.Timestamp.from_bytes(base64.b64decode(lines[1]["when"]["data"])) == stamp
    assert lines[2]["deep"] == {"k": [{"ext": 7, "data": ""}]}
    with BlockingReplay(path, speed=None) as rep:  # and the typed replay hands them over as they are
        assert next(iter(rep)).extra["x"] == msgpack.ExtType(5, b"abc")


def test_a_body_nested_too_deep_for_json_is_one_line_naming_the_byte(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A body nesting 1 000 arrays is msgpack the reader takes, and a RecursionError traceback out of json.dumps."""
    from tactiled_client.__main__ import main

    path = tmp_path / "s.tlog"
    deep = b"\x85\xa1v\x07\xa3seq\x01\xa6sensor\xa2s0\xa4type\xa6status\xa1x" + b"\x91" * 1000 + b"\xc0"
    at = _records(path, [_body(0), deep, _body(2)])[1]
    assert main(["replay", str(path), "--json"]) == 2
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == 1
    assert err == f"tactiled_client: {path}: byte {at}: message body nests too deep to print as JSON\n"


GOOD = json.dumps({"v": 7, "seq": 0, "sensor": "s", "type": "roughness", "t_start": 1.0, "t_stop": 2.0,
                   "provisional": [{"used_s": 0.5, "label": "a"}]})


@pytest.mark.parametrize(("line", "what"), [
    ('{"v":7,"sensor":"s","provisional":[{"used_s":"abc"}]}', 'provisional[0]: used_s: "abc" is not a time in seconds'),
    ('{"v":7,"sensor":"s","provisional":5}', "provisional: int, not a list"),
    ('{"v":7,"sensor":"s","provisional":{"used_s":1}}', "provisional: dict, not a list"),
    ('{"v":7,"sensor":"s","provisional":["x"]}', "provisional[0]: str, not a map"),
    ('{"v":7,"sensor":"s","t_start":[1]}', "t_start: a list is not a time in seconds"),
    ('{"v":7,"sensor":"s","t_stop":"2"}', 't_stop: "2" is not a time in seconds'),
    ('{"v":7,"sensor":"s","t_start":true}', "t_start: true is not a time in seconds"),
    ('{"v":7,"sensor":"s","t_start":Infinity}', "t_start: Infinity is not a time in seconds"),
    ('{"v":7,"sensor":"s","t_stop":1e15}', "t_stop: 1000000000000000.0 is not a time in seconds"),
    ('{"v":7,"sensor":"s","seq":100000000000000000000000}', "a value msgpack cannot hold"),
])
def test_a_wrongly_typed_replay_json_field_is_one_line_naming_line_and_field(line: str, what: str, tmp_path: Path,
                                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """``tactiled replay --json`` lines with a time that is no number, ``provisional`` no list, or an integer beyond 64 bits:
    ValueError, TypeError or OverflowError tracebacks (exit 1), or (Infinity, 1e15) an overflow in time.sleep at --speed 1.
    Malformed lines in that reader (not JSON, provisional items that are no map) were already one LogError: so are these."""
    from tactiled_client.__main__ import main

    path = tmp_path / "slides.jsonl"
    path.write_text(f"{GOOD}\n{line}\n{GOOD}\n")
    with pytest.raises(LogError) as info:
        list(BlockingReplay(path, speed=None))
    assert str(info.value).startswith(f"{path}: line 2: {what}"), info.value
    assert main(["replay", str(path), "--json", "--speed", "1000"]) == 2
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == 2 and err.startswith(f"tactiled_client: {path}: line 2: {what}") and len(err.splitlines()) == 1


def test_a_good_replay_json_line_replays_as_before(tmp_path: Path) -> None:
    """The checks leave a well-formed line's times alone: its provisional label at t_start + used_s, its final at t_stop."""
    path = tmp_path / "slides.jsonl"
    path.write_text(GOOD + "\n")
    entries = list(LogReader(path))
    assert [(e.time_mono, e.where) for e in entries] == [(1.5, "line 1"), (2.0, "line 1")]
    assert [msgpack.unpackb(e.body).get("final", True) for e in entries] == [False, True]


@pytest.mark.parametrize("frame_size", [True, False])
def test_an_mcap_decompression_bomb_is_refused_before_the_client_inflates_it(frame_size: bool, tmp_path: Path) -> None:
    """Bound: the client's MCAP reader inflated every chunk to find the roughness channels (808 MB for a 37 kB file in an
    audit): the file tactiled's reader refuses (tests/test_mcap.py) is one LogError here too, before any chunk is inflated."""
    from tests.test_mcap import _bomb

    bomb = _bomb(tmp_path / "bomb.mcap", 5_000_000, frame_size)
    with pytest.raises(LogError, match=r"bomb\.mcap: its records inflate \d+ bytes to \d+ .*a decompression bomb"):
        list(LogReader(bomb))


@pytest.mark.parametrize("endpoint", ["foo", "tcp://127.0.0.1"])
def test_an_endpoint_zeromq_cannot_parse_is_one_line_naming_it(endpoint: str, tmp_path: Path) -> None:
    """`control foo status` (and record, and a subscriber) ended in ZeroMQ's bare 'Invalid argument' traceback (an audit)."""
    from tactiled_client import BlockingSubscriber, UsageError

    with pytest.raises(UsageError, match=f"^{endpoint}: not an endpoint ZeroMQ can connect to"), BlockingSubscriber(endpoint):
        pass
    for args in (["control", endpoint, "status"], ["record", endpoint, str(tmp_path / "s.tlog"), "--seconds", "1"]):
        res = subprocess.run([sys.executable, "-m", "tactiled_client", *args], capture_output=True, text=True, timeout=60, cwd=REPO)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and f"{endpoint}: not an endpoint ZeroMQ can connect to" in lines[0], res
