"""The client library's answers to an audit: a recorder that stops, sensor filters that filter, timeouts everywhere and in
recorded time, one-line errors for bad key files and bad command lines, secret keys only the owner reads, quiet pipes."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
import zmq
from tactiled_client import schema

from tests.conftest import REPO, status_publisher


def _body(kind: str, seq: int, sensor: str = "s0", **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": sensor, "type": kind, **fields}, use_bin_type=True)
    return out


def test_record_ends_on_time_and_on_a_signal_against_a_publisher_that_never_pauses(tmp_path: Path) -> None:
    """It drained until 200 ms of quiet: against a message every 100 ms ``--seconds 1`` ran for 410 s and ignored SIGTERM."""
    from tactiled_client.record import record

    endpoint = f"ipc://{tmp_path}/steady"
    done: list[int] = []
    with status_publisher(endpoint):
        thread = threading.Thread(target=lambda: done.append(record(endpoint, tmp_path / "a.tlog", seconds=0.5)), daemon=True)
        start = time.monotonic()
        thread.start()
        thread.join(5.0)
        assert not thread.is_alive(), "record(seconds=0.5) still running after 5 s"
    assert time.monotonic() - start < 5.0 and done and done[0] > 0
    with status_publisher(endpoint.replace("steady", "steady2")) as subscribed:
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


def _subscriptions(xpub: zmq.Socket[bytes], wanted: set[bytes], timeout: float = 10.0) -> None:
    """Wait until ``xpub`` has seen a subscription to each of ``wanted`` (topics), so that what it sends next is delivered."""
    seen: set[bytes] = set()
    deadline = time.monotonic() + timeout
    while not wanted <= seen:
        left = int((deadline - time.monotonic()) * 1000)
        assert left > 0 and xpub.poll(left), f"subscribed to {sorted(seen)}, never to {sorted(wanted - seen)}"
        seen.add(xpub.recv()[1:])


def test_a_sensor_filter_takes_that_sensor_alone_with_or_without_topics(tmp_path: Path) -> None:
    """``sensor=`` was dropped without ``topics`` (every sensor's messages came), and with them matched a prefix (finger10)."""
    from tactiled_client import BlockingReplay, BlockingSubscriber
    from tactiled_client.log import LogWriter

    sent = [(b"status/finger10", _body("status", 0, "finger10")), (b"roughness/other", _body("roughness", 0, "other")),
            (b"status/finger1", _body("status", 0, "finger1")), (b"roughness/finger10", _body("roughness", 0, "finger10")),
            (b"roughness/finger1", _body("roughness", 0, "finger1"))]
    endpoint = f"ipc://{tmp_path}/pub"
    xpub: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    xpub.setsockopt(zmq.LINGER, 0)
    xpub.bind(endpoint)
    try:
        with BlockingSubscriber(endpoint, sensor="finger1", timeout=10) as sub:
            _subscriptions(xpub, {b"status/finger1", b"roughness/finger1"})
            for frames in sent:
                xpub.send_multipart(list(frames))
            got = [sub.receive(), sub.receive()]
        assert [(m.type, m.sensor) for m in got] == [("status", "finger1"), ("roughness", "finger1")]
    finally:
        xpub.close(linger=0)
    with LogWriter(tmp_path / "s.tlog") as log:
        for i, frames in enumerate(sent):
            log.write(list(frames), float(i), float(i))
    with BlockingReplay(tmp_path / "s.tlog", sensor="finger1", speed=None) as rep:
        assert [(m.type, m.sensor) for m in rep] == [("status", "finger1"), ("roughness", "finger1")]
    with BlockingReplay(tmp_path / "s.tlog", topics=["roughness"], sensor="finger1", speed=None) as rep:
        assert [(m.type, m.sensor) for m in rep] == [("roughness", "finger1")]


def test_the_async_subscriber_takes_a_timeout_per_receive_as_the_others_do(tmp_path: Path) -> None:
    """``Subscriber.receive()`` had no ``timeout=`` (``Replay`` and ``BlockingSubscriber`` have it): a TypeError."""
    import asyncio

    from tactiled_client import NoData, Subscriber

    async def run() -> None:
        async with Subscriber(f"ipc://{tmp_path}/nobody") as sub:  # no timeout of its own: would wait for ever
            with pytest.raises(NoData, match=r"for 0\.05 s"):
                await asyncio.wait_for(sub.receive(timeout=0.05), 10)

    asyncio.run(run())


def _gap_session(path: Path) -> None:
    """Four status messages with a 4 s silence in the middle of the recorded session."""
    from tactiled_client.log import LogWriter

    with LogWriter(path) as log:
        for seq, t in enumerate([100.0, 100.1, 104.1, 104.2]):
            log.write([b"status/s0", _body("status", seq, state="idle")], t, 1.7e9 + t)


@pytest.mark.parametrize("speed", [None, 20.0])
def test_a_replays_timeout_is_in_recorded_time_at_every_speed(speed: float | None, tmp_path: Path) -> None:
    """The timeout was measured in wall time: a 4 s recorded silence and timeout=3 gave no NoData at speed None or 2."""
    import asyncio

    from tactiled_client import BlockingReplay, EndOfLog, NoData, Replay

    _gap_session(tmp_path / "gap.tlog")
    seen: list[str] = []
    with BlockingReplay(tmp_path / "gap.tlog", speed=speed, timeout=3.0) as rep:
        while True:
            try:
                seen.append(f"seq{rep.receive().seq}")
            except EndOfLog:
                break
            except NoData as exc:
                seen.append(str(exc).split(": ", 1)[1])
    assert seen == ["seq0", "seq1", "no message for 3 s of recorded time", "seq2", "seq3"]

    async def run() -> list[str]:
        out: list[str] = []
        async with Replay(tmp_path / "gap.tlog", speed=speed) as sub:
            while True:
                try:
                    out.append(f"seq{(await sub.receive(timeout=3.0)).seq}")
                except EndOfLog:
                    return out
                except NoData:
                    out.append("NoData")

    assert asyncio.run(run()) == ["seq0", "seq1", "NoData", "seq2", "seq3"]


def test_a_bad_curve_key_file_is_one_line_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A missing key file or one that is no certificate was a traceback and exit 1 (OSError, ValueError from pyzmq)."""
    from tactiled_client import BlockingSubscriber, UsageError
    from tactiled_client.__main__ import main

    (tmp_path / "notes.txt").write_text("not a certificate\n")
    endpoint = f"ipc://{tmp_path}/nobody"
    for bad, what in ((tmp_path / "missing.key", "no such certificate file"), (tmp_path / "notes.txt", "not a ZeroMQ certificate")):
        with pytest.raises(UsageError, match=what):
            BlockingSubscriber(endpoint, curve=(str(bad), str(bad)))
        for argv in (["record", endpoint, str(tmp_path / "s.tlog"), "--seconds", "0.1"], ["control", endpoint, "status", "--timeout", "0.1"]):
            assert main([*argv, "--curve", str(bad), str(bad)]) == 2
            err = capsys.readouterr().err.strip()
            assert err == f"tactiled_client: {bad}: {what}" or err.startswith(f"tactiled_client: {bad}: {what} ("), err
    assert not (tmp_path / "s.tlog").exists()


def test_curve_keys_writes_the_secret_key_for_its_owner_alone(tmp_path: Path) -> None:
    """``tactiled curve-keys`` wrote NAME.key_secret world-readable (0644 under umask 022), and --force kept an old file's mode."""
    import os
    import stat

    import zmq.auth

    from tactiled.service.publish import create_curve_pair

    old = os.umask(0o022)
    try:
        public, secret = create_curve_pair(tmp_path / "keys", "daemon")
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600 and stat.S_IMODE(public.stat().st_mode) == 0o644
        secret.chmod(0o644)  # a pair made by the old code, replaced
        public2, secret2 = create_curve_pair(tmp_path / "keys", "daemon", force=True)
    finally:
        os.umask(old)
    assert stat.S_IMODE(secret2.stat().st_mode) == 0o600
    assert sorted(p.name for p in (tmp_path / "keys").iterdir()) == ["daemon.key", "daemon.key_secret"]  # no staging left
    pub, sec = zmq.auth.load_certificate(secret2)
    assert sec and zmq.auth.load_certificate(public2) == (pub, None)


def test_replay_json_into_a_pipe_closed_early_is_quiet(tmp_path: Path) -> None:
    """``replay FILE --json | head -1`` printed a BrokenPipeError traceback."""
    from tactiled_client.log import LogWriter

    with LogWriter(tmp_path / "s.tlog") as log:  # far more than a pipe holds (64 kB): the replay is still writing when it closes
        for seq in range(5000):
            log.write([b"status/s0", _body("status", seq, state="idle")], float(seq), float(seq))
    proc = subprocess.Popen([sys.executable, "-m", "tactiled_client", "replay", str(tmp_path / "s.tlog"), "--json"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.readline().startswith('{"topic": "status/s0"')
    proc.stdout.close()  # what head does after its line
    err = proc.stderr.read()
    assert proc.wait(30) == 1 and err == "", err


def test_publishing_a_truncated_log_warns_as_the_json_replay_does(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``replay trunc.tlog --publish`` said nothing of the truncation that ``--json`` warns about."""
    from tactiled_client.__main__ import main

    _gap_session(tmp_path / "s.tlog")
    (tmp_path / "cut.tlog").write_bytes((tmp_path / "s.tlog").read_bytes()[:-5])  # a recorder killed mid-write
    assert main(["replay", str(tmp_path / "cut.tlog"), "--publish", f"ipc://{tmp_path}/pub", "--speed", "1000"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and err[0].startswith(f"warning: {tmp_path / 'cut.tlog'}: ends inside a record at byte "), err
    assert err[1] == f"{tmp_path / 'cut.tlog'}: published 3 messages on ipc://{tmp_path}/pub"
    assert not (tmp_path / "pub").exists()  # its socket's file removed as it stops


def test_every_client_command_in_the_docs_parses_and_messages_md_names_the_schema_version() -> None:
    """docs/integrations.md showed ``python -m tactiled_client replay slides.mcap``, which exits 2 (--json or --publish is
    required); docs/messages.md's title said schema version 6 where the table and the wire say 7."""
    import io
    import re
    import shlex

    from tactiled_client.__main__ import build_parser

    docs = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    commands = []
    for doc in docs:
        if doc.name == "cli.md":  # the parser's own help
            continue
        text = doc.read_text(encoding="utf-8")
        commands += [(doc.name, c) for c in re.findall(r"`(python -m tactiled_client [^`]*)`", text)]
        commands += [(doc.name, c.split("#")[0]) for c in re.findall(r"^\s*(python -m tactiled_client .*)$", text, flags=re.M)]
    bad = []
    for name, command in commands:
        if "|" in command:  # a synopsis (record|replay), not a command line
            continue
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                build_parser().parse_args(shlex.split(command)[3:])
        except SystemExit as exc:
            if exc.code:
                bad.append(f"{name}: {command}: {err.getvalue().strip().splitlines()[-1]}")
    assert not bad, "\n".join(bad)
    assert len(commands) >= 6
    title = (REPO / "docs" / "messages.md").read_text(encoding="utf-8").splitlines()[0]
    assert title == f"# Messages (schema version {schema.SCHEMA_VERSION})"


def test_a_message_that_is_not_tactileds_is_skipped_and_counted_not_raised(tmp_path: Path) -> None:
    """Three frames, a body that is no msgpack or no map, an unknown type without seq raised ValueError, FormatError or
    TypeError out of receive(): not a ClientError, so it ended a controller that catches the library's errors."""
    from tactiled_client import BlockingReplay, BlockingSubscriber
    from tactiled_client.log import LogWriter

    noseq: bytes = msgpack.packb({"v": 7, "sensor": "s0", "type": "force"})
    strseq: bytes = msgpack.packb({"v": 7, "seq": "a", "sensor": "s0", "type": "status"})
    bad = [[b"roughness/s0", b"x", b"y"], [b"roughness/s0", b"\xc1\xc1"], [b"roughness/s0", msgpack.packb([1, 2])],
           [b"force/s0", noseq], [b"status/s0", strseq]]
    endpoint = f"ipc://{tmp_path}/pub"
    xpub: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    xpub.setsockopt(zmq.LINGER, 0)
    xpub.bind(endpoint)
    try:
        with BlockingSubscriber(endpoint, timeout=10) as sub:
            _subscriptions(xpub, {b""})
            for frames in [*bad, [b"status/s0", _body("status", 0, state="idle")]]:
                xpub.send_multipart(frames)
            msg = sub.receive()
        assert (msg.type, msg.seq, sub.malformed) == ("status", 0, 5)
        assert sub.last_malformed == "status/s0: seq is str, not int"
    finally:
        xpub.close(linger=0)
    with LogWriter(tmp_path / "s.tlog") as log:  # a recorder keeps every two-frame message; the replay skips them alike
        log.write([b"force/s0", noseq], 1.0, 1.0)
        log.write([b"status/s0", strseq], 2.0, 2.0)
        log.write([b"status/s0", _body("status", 0, state="idle")], 3.0, 3.0)
    with BlockingReplay(tmp_path / "s.tlog", speed=None) as rep:
        assert [m.type for m in rep] == ["status"] and rep.malformed == 2


@pytest.mark.parametrize("argv", [[], ["replay", "s.tlog"], ["record", "ipc:///x", "s.tlog", "--topics", "nope"], ["control", "ipc:///x", "fly"]])
def test_a_client_usage_error_is_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """The module docstring promises one line on stderr; argparse printed its whole usage first (7 lines for replay)."""
    from tactiled_client.__main__ import main

    with pytest.raises(SystemExit) as done:
        main(argv)
    err = capsys.readouterr().err
    assert done.value.code == 2 and len(err.strip().splitlines()) == 1 and "error:" in err and "--help" in err, err
