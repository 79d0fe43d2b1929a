"""A known field of the wrong type in an otherwise valid message never reaches a controller: the live subscriber and the
session-log replay skip it as a malformed message (counted, one line naming the topic, the field, its declared type and
what came) and go on; unknown fields stay accepted whatever their type, an int is a float, a bool is no int."""

from __future__ import annotations

from pathlib import Path

import msgpack
import pytest
from tactiled_client import BlockingReplay, BlockingSubscriber, Roughness, schema
from tactiled_client.log import LogWriter

from tests.conftest import xpub_socket

# (field, wrong value, the line's end): each turned into a Roughness and handed to the controller before
BAD = [("confidence", "high", "confidence is str 'high', not float | None"),
       ("slide_id", [1, 2], "slide_id is list [1, 2], not int"),
       ("label", 3, "label is int 3, not str | None"),
       ("slide_id", True, "slide_id is bool True, not int"),  # msgpack keeps bool apart from int: True is no slide id
       ("t_start", False, "t_start is bool False, not float"),
       ("final", 1, "final is int 1, not bool"),
       ("quality", None, "quality is NoneType None, not dict[str, Any]"),
       ("window", "0:10", "window is str '0:10', not list[int]")]


def _roughness(seq: int, **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": "s0", "type": "roughness", "label": "Ra1.18",
                                "confidence": 0.8, "slide_id": seq, **fields}, use_bin_type=True)
    return out


def _stream() -> list[list[bytes]]:
    """Each wrong-typed message followed by a good one; last, good ones whose types a reader must take."""
    frames: list[list[bytes]] = []
    for i, (name, value, _) in enumerate(BAD):
        frames += [[b"roughness/s0", _roughness(2 * i, **{name: value})], [b"roughness/s0", _roughness(2 * i + 1)]]
    n = 2 * len(BAD)
    frames += [[b"roughness/s0", _roughness(n, confidence=1, t_start=2, label=None)],  # an int where a float is declared
               [b"roughness/s0", _roughness(n + 1, future_field={"any": [b"thing"]}, other=True)]]  # unknown fields: any type
    return frames


def _check(got: list[tuple[Roughness, int, str | None]]) -> None:
    """``got``: (message, malformed count, last_malformed) after each message received."""
    n = 2 * len(BAD)
    assert [m.seq for m, _, _ in got] == [*range(1, n, 2), n, n + 1]
    for i, (msg, malformed, line) in enumerate(got[:len(BAD)]):
        assert malformed == i + 1 and msg.missed == (1 if i else 0)  # counted; its seq is missing (none before the first)
        assert line == f"roughness/s0: {BAD[i][2]}"
    assert all(m.label == "Ra1.18" and m.confidence == 0.8 and m.slide_id == m.seq for m, _, _ in got[:len(BAD)])
    took_int, took_unknown = got[-2][0], got[-1][0]
    assert (took_int.confidence, took_int.t_start, took_int.label, took_int.missed) == (1, 2, None, 0)
    assert took_unknown.extra == {"future_field": {"any": [b"thing"]}, "other": True} and got[-1][1] == len(BAD)


def test_the_live_subscriber_skips_a_wrong_typed_field_and_goes_on(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/pub"
    with xpub_socket(endpoint) as xpub, BlockingSubscriber(endpoint, topics=["roughness"], timeout=20.0) as sub:
        assert xpub.poll(20_000), "the subscriber never subscribed"
        xpub.recv()
        for frames in _stream():
            xpub.send_multipart(frames)
        got = []
        for _ in range(len(BAD) + 2):
            msg = sub.receive()
            assert isinstance(msg, Roughness)
            got.append((msg, sub.malformed, sub.last_malformed))
    _check(got)


def test_a_session_log_replay_skips_a_wrong_typed_field_and_goes_on(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "s.tlog") as log:
        for i, frames in enumerate(_stream()):
            log.write(frames, 100.0 + i, 1.7e9 + i)
    got = []
    with BlockingReplay(tmp_path / "s.tlog", speed=None) as rep:
        for msg in rep:
            assert isinstance(msg, Roughness)
            got.append((msg, rep.malformed, rep.last_malformed))
    _check(got)


def test_parse_names_the_field_and_the_daemon_builds_on(tmp_path: Path) -> None:
    """``schema.parse`` raises :class:`schema.FieldTypeError` (a ValueError); the builders the daemon uses are not checked."""
    with pytest.raises(schema.FieldTypeError, match=r"^confidence is str 'high', not float \| None$") as info:
        schema.parse("roughness/s0", msgpack.unpackb(_roughness(0, confidence="high")))
    assert (info.value.field, info.value.expected) == ("confidence", "float | None") and isinstance(info.value, ValueError)
    status = schema.parse("status/s0", {"v": 8, "seq": 0, "sensor": "s0", "type": "status", "clock_index": None, "level": [0.1],
                                        "shadow": {"model": "m"}, "fs_clock": 20000})
    assert isinstance(status, schema.Status) and status.fs_clock == 20000 and status.shadow == {"model": "m"}
