"""The ingest core: block invariance, gap and channel policies, the serial source, and replay of a raw capture against the live daemon."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import subprocess
import threading
import time
import tracemalloc
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import serial
import zmq
from tactiled_client import BlockingSubscriber, Roughness, Slide, Status

from tactiled.board.frames import encode_frame, encode_frames
from tactiled.board.serialsource import CONNECTED, DISCONNECTED, MemorySource, SerialSource, port_fd
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideEnded, SlideResult
from tactiled.files.capture import read_chunks, recording_bytes
from tactiled.files.recording import Recording
from tactiled.learn.model import load_model
from tactiled.run.ingest import Batch, Ingest, max_gap_for
from tactiled.run.stream import Stream
from tactiled.service.daemon import Daemon
from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file
from tests.conftest import board_and_daemon, run_cli, standing_finals, tactiled_cmd, wait_for

FS = 20_000.0


def _stream(seed: int = 4, first: int = 1000) -> tuple[bytes, np.ndarray]:
    """A few seconds of simulated slides as the board's bytes, with corrupted frames and garbage between frames."""
    sim = simulate_file(SimParams(), pick_surfaces("Ra2.29")[0], 2, seed)
    frames = [bytearray(encode_frame(first + i, sim.samples[i:i + 20])) for i in range(0, sim.samples.shape[0] - 19, 20)]
    rng = np.random.default_rng(seed)
    for k in rng.choice(len(frames), 12, replace=False):
        frames[k][int(rng.integers(2, len(frames[k])))] ^= 0x5A
    for k in rng.choice(len(frames), 12, replace=False):
        frames[k] = bytearray(rng.integers(0, 256, 17, dtype=np.uint8).tobytes()) + frames[k]
    return b"".join(bytes(f) for f in frames), sim.samples


def _events(data: bytes, chunk: int, min_batch: int = 1) -> list[tuple[object, ...]]:
    stream = Stream(Config(), load_model(), min_batch=min_batch)
    events = [ev for i in range(0, len(data), chunk) for ev in stream.feed_bytes(data[i:i + chunk]).events]
    return [_key(ev) for ev in events + stream.finish().events]


def _key(ev: PipelineEvent) -> tuple[object, ...]:
    if isinstance(ev, SlideResult):
        return ("result", ev.slide_id, ev.start, ev.stop, ev.window, ev.label, ev.reason, ev.confidence, ev.final)
    return (type(ev).__name__, *vars(ev).values())


def test_events_do_not_depend_on_how_the_bytes_are_cut() -> None:
    data, _ = _stream()
    whole = _events(data, len(data))
    assert any(k[0] == "result" and k[-1] for k in whole)  # final labels came
    assert _events(data, 4096) == whole
    assert _events(data, 7) == whole
    assert _events(data[: len(data) // 3], 1) == _events(data[: len(data) // 3], len(data))
    assert _events(data, 4096, min_batch=800) == whole  # batching is invisible too


def _frames(first: int, n: int, channels: int = 2, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    return encode_frames(first, rng.integers(-500, 500, (n * 20, channels)).astype(np.int16))


@pytest.mark.parametrize(("jump", "counted"), [(2**31 + 12345, False), (2**24, True), (2**31 - 1 - 1000, True)])
def test_a_huge_forward_jump_costs_constant_memory(jump: int, counted: bool) -> None:
    """A jump the 32-bit counter can say (below 2**31) is lost samples, however long; one it cannot (2**31 ahead is as far
    behind) is a restart. Either way nothing is proportional to the gap, and a slide in progress would end before it."""
    stream = Stream(Config(), None)
    stream.feed_bytes(_frames(5000, 50))
    tracemalloc.start()
    try:
        after = stream.feed_bytes(_frames((5000 + 1000 + jump) % 2**32, 50, seed=1)).batches
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4 << 20, peak  # nothing proportional to the gap (2**24 int16 pairs alone would be 64 MiB)
    if counted:
        assert stream.stats.restarts == 0 and stream.stats.samples_lost == jump
        assert [(b.index, b.lost, b.restart) for b in after] == [(6000 + jump, jump, False)]  # positions stay sensor time
        assert stream.live.ring.end == 7000 + jump
    else:
        assert stream.stats.restarts == 1 and stream.stats.samples_lost == 0
        assert [(b.index, b.restart) for b in after] == [(6000, True)]  # the timeline continues where it was
        assert stream.live.ring.end == 7000


@pytest.mark.parametrize("restart", [True, False])
def test_a_slide_cut_by_a_board_restart_or_a_gap_past_the_ring_ends_interrupted(restart: bool) -> None:
    """The board restarts (its index back to 0), or 30 s of samples are lost with the port open, in the middle of a slide:
    the slide ends at the last sample before, reason ``interrupted`` (``end_of_stream`` is for a stream that ends: a
    subscriber reads it as the daemon stopping), its final label follows, and the stream goes on (an outside audit)."""
    sim = simulate_file(SimParams(), pick_surfaces("Ra2.29")[0], 2, 4)
    cut = (sim.truth[0].start + sim.truth[0].stop) // 2 // 20 * 20
    stream = Stream(Config(), load_model())
    first = 1_000_000
    events = stream.feed_bytes(encode_frames(first, sim.samples[:cut])).events
    after = 0 if restart else first + cut + int(30 * FS)
    events += stream.feed_bytes(encode_frames(after, sim.samples[cut:])).events + stream.finish().events
    assert (stream.stats.restarts, stream.stats.samples_lost > 0) == ((1, False) if restart else (0, True))
    ends = [ev for ev in events if isinstance(ev, SlideEnded)]
    assert (ends[0].reason, ends[0].stop) == ("interrupted", first + cut)
    assert any(isinstance(ev, SlideResult) and ev.final and ev.slide_id == ends[0].slide_id for ev in events)
    assert [ev.reason for ev in ends[1:]] == ["quiet", "quiet"]  # the rest of that slide, and the next one


def test_a_slide_cut_by_a_load_shed_ends_interrupted_too() -> None:
    """The daemon sheds load in the middle of a slide: it ends ``interrupted``, as at a board restart, not
    ``end_of_stream`` (which a live subscriber reads as the daemon stopping; a review of the restart's change)."""
    sim = simulate_file(SimParams(), pick_surfaces("Ra2.29")[0], 2, 4)
    cut = (sim.truth[0].start + sim.truth[0].stop) // 2 // 20 * 20
    stream = Stream(Config(), load_model())
    stream.feed_bytes(encode_frames(0, sim.samples[:cut]))
    ends = [ev for ev in stream.shed().events if isinstance(ev, SlideEnded)]
    assert [(ev.reason, ev.stop) for ev in ends] == [("interrupted", cut)]


def test_a_gap_within_the_ring_is_lost_samples_not_a_restart() -> None:
    ingest = Ingest(2, max_gap=max_gap_for(20.0, FS))
    ingest.feed(_frames(0, 10))
    (b,) = ingest.feed(_frames(200 + 300_000, 10))
    assert (b.index, b.lost, b.restart) == (300_200, 300_000, False)
    assert ingest.stats.samples_lost == 300_000 and ingest.stats.restarts == 0


def test_foreign_channel_frames_never_move_the_index() -> None:
    ingest = Ingest(2, max_gap=max_gap_for(20.0, FS))
    data = b"".join(_frames(k * 20, 1, seed=k) + encode_frame(2**31 + 7 * k, np.ones((20, 8), dtype=np.int16)) for k in range(30))
    batches = ingest.feed(data) + ingest.flush()
    assert [(b.index, b.samples.shape[0]) for b in batches] == [(0, 600)]
    st = ingest.stats
    assert (st.channel_errors, st.samples, st.samples_lost, st.restarts) == (30, 600, 0, 0)


def test_recording_bytes_round_trip_through_the_core() -> None:
    samples = np.arange(4000, dtype=np.int16).reshape(2000, 2)
    rec = Recording(samples, FS, 1.0, first_index=77, lost=np.array([[400, 100]]))
    ingest = Ingest(2, max_gap=10_000)
    batches = ingest.feed(recording_bytes(rec)) + ingest.flush()
    assert [(b.index, b.lost) for b in batches] == [(77, 0), (577, 100)]
    got = np.concatenate([b.samples for b in batches])
    assert np.array_equal(got, np.concatenate([samples[:400], samples[500:]]))


def _pty_frames(n_frames: int, first: int = 0) -> bytes:
    return _frames(first, n_frames)


class _FailingTee:
    """A capture file whose first write fails: an exception inside the reader thread itself."""

    def __init__(self) -> None:
        self.writes = 0

    def write(self, data: bytes) -> int:
        self.writes += 1
        if self.writes == 1:
            raise RuntimeError("tee broke")
        return len(data)

    def flush(self) -> None:
        pass


def test_opening_the_port_keeps_what_the_board_sent_before() -> None:
    """pyserial flushes a port's input when it opens it; bytes already in the tty (a replug) are kept (the source drops them
    itself at its first open only: tests/test_loss_counting.py)."""
    from tactiled.board.serialsource import KeepInputSerial

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        os.write(master, b"frames sent before the open")
        port = KeepInputSerial(os.ttyname(slave), timeout=0)
        try:
            assert port.read(100) == b"frames sent before the open"
            os.write(master, b"stale")
            port.reset_input_buffer()  # an explicit reset still resets
            assert port.read(100) == b""
        finally:
            port.close()
    finally:
        os.close(master)
        os.close(slave)


def test_a_port_has_one_reader_and_a_second_is_told_why(tmp_path: Path) -> None:
    """A recorder started beside a running daemon would take part of each one's bytes: ports open exclusively, and the
    second opener gets one line saying another process has it (the daemon: the same reason, and it keeps retrying)."""
    from tactiled.board.serialsource import KeepInputSerial, check_port
    from tactiled.errors import DeviceError

    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "tty"
    link.symlink_to(os.ttyname(slave))
    first = KeepInputSerial(str(link), timeout=0, exclusive=True)
    try:
        with pytest.raises(DeviceError, match="another process has it open"):
            check_port(os.ttyname(slave))  # the same tty under its own name
        res = run_cli("record", "--port", str(link), "--seconds", "1", "-o", str(tmp_path / "r.npz"))
        assert res.returncode == 2 and "another process has it open (a running daemon or recorder?)" in res.stderr, res.stderr
    finally:
        first.close()
        os.close(master)
        os.close(slave)
    assert not (tmp_path / "r.npz").exists()


def test_serial_source_survives_reader_and_consumer_failures_and_counts_them() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    got: list[bytes] = []
    states: list[tuple[str, str]] = []

    async def main() -> SerialSource:
        more = asyncio.Event()
        calls = 0

        def on_bytes(data: bytes) -> None:
            nonlocal calls
            calls += 1
            if calls == 1:
                raise ValueError("consumer broke")  # the first bytes that reach the consumer make it fail
            got.append(data)
            more.set()

        source = SerialSource(path, on_bytes, lambda s, d: states.append((s, d)), read_interval_s=0.005, retry_max_s=0.05,
                              tee=_FailingTee())  # type: ignore[arg-type]
        task = asyncio.create_task(source.run())
        deadline = asyncio.get_running_loop().time() + 20
        while not got:  # write until bytes reach the consumer after both failures (the source may still be reopening)
            assert asyncio.get_running_loop().time() < deadline, states
            os.write(master, b"y" * 10)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(more.wait(), 0.5)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return source

    try:
        source = asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert source.errors == 2 and source.reconnects == 1  # the tee's failure reconnected; the consumer's did not
    assert got and set(b"".join(got)) == set(b"y")
    assert [s for s, _ in states] == [CONNECTED, DISCONNECTED, CONNECTED]
    assert "reader error RuntimeError: tee broke" in states[1][1]


def test_daemon_on_a_memory_source_ends_the_stream_and_publishes_every_event(tmp_path: Path) -> None:
    data, _ = _stream(seed=6)
    config = Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub", "publish.status_interval_s": 0.2})
    expected = [k for k in _events(data, 4096) if k[0] == "result" and k[-1]]
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"roughness")
    sub.setsockopt(zmq.SUBSCRIBE, b"status")
    got: list[dict[str, object]] = []

    def chunks() -> Iterator[bytes]:
        """Nothing until a status message arrives (the subscriptions have reached the publisher), then the stream."""
        deadline = time.monotonic() + 30
        while not sub.poll(0):
            assert time.monotonic() < deadline, "no status message from the daemon"
            yield b""  # the source yields to the loop between chunks: the status task runs
        yield from (data[i:i + 920] for i in range(0, len(data), 920))

    async def main() -> None:
        daemon = Daemon(config, load_model(), source_factory=lambda on_bytes, on_state: MemorySource(chunks(), on_bytes, on_state))
        sub.connect(daemon.endpoint)
        await daemon.run()  # returns at the end of the stream
        assert daemon.stream.stats.crc_errors + daemon.stream.stats.bad_headers >= 12

    asyncio.run(main())
    import msgpack

    while sub.poll(2000):
        topic, *_, body = sub.recv_multipart()
        if topic.startswith(b"roughness"):
            got.append(msgpack.unpackb(body))
    sub.close(linger=0)
    finals = [(m["start"], m["stop"], m["label"]) for m in got if m["final"]]
    assert finals == [(k[2], k[3], k[5]) for k in expected] and finals


def test_run_no_wait_exits_at_once_and_waiting_says_so_once(tmp_path: Path) -> None:
    missing = str(tmp_path / "missing")
    res = subprocess.run(tactiled_cmd("run", "--port", missing, "--no-wait", "--no-model", "--publish", f"ipc://{tmp_path}/a"),
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [f"tactiled: error: {missing}: no such serial device"]
    cfg = tmp_path / "c.toml"
    cfg.write_text("[publish]\nstatus_interval_s = 0.05\n")
    endpoint = f"ipc://{tmp_path}/b"
    with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as sub:
        proc = subprocess.Popen(tactiled_cmd("run", "--config", str(cfg), "--port", missing, "--no-model", "--publish", endpoint),
                                stderr=subprocess.PIPE, text=True)
        try:
            seen: list[Status] = []
            wait_for(lambda: seen.append(sub.receive()) or len(seen) >= 10, timeout=30, what="ten statuses")  # type: ignore[func-returns-value]
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert all(s.state == "disconnected" for s in seen)
    assert sum("waiting for the device" in line for line in err.splitlines()) == 1, err


def test_a_socket_url_port_delivers_every_byte(tmp_path: Path) -> None:
    """``sensor.port = "socket://host:port"`` (a network serial bridge): the daemon reads all the bridge sends, not a byte per
    read (pyserial's socket handler says one byte is waiting whatever has come), and keeps what came before the bridge closed."""
    sim = simulate_file(SimParams(), pick_surfaces("Ra2.29")[0], 2, 3)
    n = sim.samples.shape[0] // 20 * 20
    data = encode_frames(0, sim.samples[:n])
    server = socket.create_server(("127.0.0.1", 0))
    host, port = server.getsockname()
    connected = threading.Event()

    def serve() -> None:
        with server, server.accept()[0] as conn:
            connected.wait(60)  # pyserial's open() drops what the socket holds: send once the daemon says it is connected
            conn.sendall(data)  # then the bridge closes at once: the daemon says it is disconnected

    threading.Thread(target=serve, daemon=True).start()
    cfg, raw, endpoint = tmp_path / "c.toml", tmp_path / "cap.bin", f"ipc://{tmp_path}/pub"
    cfg.write_text("[sensor]\nallow_url = true\n[publish]\nstatus_interval_s = 0.05\n")
    seen: list[Status] = []

    def status() -> Status:
        seen.append(sub.receive())
        if seen[-1].state == "connected":
            connected.set()
        return seen[-1]

    with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as sub:
        proc = subprocess.Popen(tactiled_cmd("run", "--config", str(cfg), "--port", f"socket://{host}:{port}", "--raw", str(raw),
                                             "--no-model", "--publish", endpoint), stderr=subprocess.PIPE, text=True)
        try:
            wait_for(lambda: (s := status()).samples >= n and s.state == "disconnected", timeout=60, what=f"{n} samples, then the close")
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert (seen[-1].samples, seen[-1].samples_lost, seen[-1].crc_errors) == (n, 0, 0), err
    assert raw.read_bytes() == data


def test_a_read_takes_more_than_the_4_kib_a_tty_hands_out_at_once() -> None:
    """A tty's read returns at most 4095 bytes; the source reads on until the kernel has no more, so a read period that
    holds more than 4 KiB of the board's bytes (20 kHz at a 50 ms period, more channels, a loaded host) loses nothing."""
    master, slave = os.openpty()
    tty.setraw(slave)
    data = bytes(range(256)) * 240  # 60 kB: the pty holds ~20 kB, so the writer waits for the reader
    got: list[bytes] = []
    done = threading.Event()

    def on_bytes(chunk: bytes) -> None:
        got.append(chunk)
        if sum(map(len, got)) >= len(data):
            done.set()

    source = SerialSource(os.ttyname(slave), on_bytes, read_interval_s=0.2)  # one delivery per read (start/stop)
    try:
        source.start()
        writer = threading.Thread(target=lambda: [os.write(master, data[i:i + 920]) for i in range(0, len(data), 920)], daemon=True)
        wait_for(lambda: source.connected, what="the source's open")  # (it drops what the port held before: nothing yet)
        writer.start()
        assert done.wait(60), f"{sum(map(len, got))} of {len(data)} bytes"
        source.stop()
    finally:
        os.close(master)
        os.close(slave)
    assert b"".join(got) == data
    assert max(map(len, got)) > 4096, [len(c) for c in got]  # a read took more than one tty read's worth


def test_url_ports_are_read_by_their_socket_or_by_read(tmp_path: Path) -> None:
    """socket:// by its socket's fd (pyserial's read() there drops what it gathered at the close); loop:// and rfc2217://
    have no fd of their own (io's fileno raises): read through pyserial, not taken for a disconnect."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        host, port = server.getsockname()
        with contextlib.closing(serial.serial_for_url(f"socket://{host}:{port}", timeout=0)) as sock_port:
            assert port_fd(sock_port) == sock_port._socket.fileno()
    with contextlib.closing(serial.serial_for_url("loop://", timeout=0)) as loop_port:
        assert port_fd(loop_port) is None


def test_a_port_that_fails_before_a_byte_is_reopened_with_backoff() -> None:
    """A bridge that accepts each connection and closes it at once: the source reopens after 0.05, 0.1, 0.2 ... s, not in
    a tight loop (a replug that had given bytes is reopened at once)."""
    opened: list[float] = []
    with socket.create_server(("127.0.0.1", 0)) as server:
        server.settimeout(30)
        host, port = server.getsockname()
        source = SerialSource(f"socket://{host}:{port}", lambda b: None, retry_initial_s=0.05, retry_max_s=2.0)
        source.start()
        try:
            while len(opened) < 6:
                conn, _ = server.accept()
                opened.append(time.monotonic())
                conn.close()
        finally:
            source.stop()
    gaps = np.diff(opened)  # each: pyserial's open (~0.3 s here), then the wait, which doubles from 0.05 s
    assert gaps[-1] - gaps[0] >= 0.5, gaps  # 0.8 - 0.05 s expected


def test_run_no_wait_and_record_refuse_a_socket_url_nothing_listens_on(tmp_path: Path) -> None:
    """As for a missing tty: one line, exit 2, at once (they retried for ever)."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        host, port = server.getsockname()  # closed below: nothing listens there
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sensor]\nallow_url = true\n")
    url = f"socket://{host}:{port}"
    for args in (("run", "--no-wait", "--no-model", "--publish", f"ipc://{tmp_path}/p"), ("record", "--seconds", "1", "-o", str(tmp_path / "r.npz"))):
        res = subprocess.run(tactiled_cmd(*args, "--config", str(cfg), "--port", url), capture_output=True, text=True, timeout=60)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"tactiled: error: {url}: cannot open: "), res.stderr


def test_replay_of_the_raw_capture_gives_the_live_daemons_events(tmp_path: Path) -> None:
    """The daemon writes what it reads (run --raw); replay x.bin through the decoder gives the same slides and labels."""
    raw = tmp_path / "cap.bin"
    messages: list[object] = []
    with board_and_daemon(tmp_path, "--raw", str(raw), surfaces=4, seed=8, corrupt=0.01, drop=0.005, garbage=0.01,
                          first_index=2**32 - 100_000) as live, \
            BlockingSubscriber(live.endpoint, topics=["roughness", "slide"], timeout=30) as sub:  # the 32-bit index wraps 5 s in
        # four final labels that stand for good: a later slide has started, so no "resumed" can withdraw them
        wait_for(lambda: messages.append(sub.receive()) or (len(standing_finals(messages)) >= 4  # type: ignore[func-returns-value]
                                                            and isinstance(messages[-1], Slide) and messages[-1].event == "start"),
                 timeout=120, what="four labels and the next slide")
        err = live.stop()
    assert live.proc.returncode == 0, err
    live = [(m.slide_id, m.start, m.stop, m.label, m.reason) for m in standing_finals(messages)]
    res = subprocess.run(tactiled_cmd("replay", "--json", str(raw)), capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    base = Ingest(2, max_gap=10_000).feed(next(read_chunks(raw)))[0].index  # the capture's first index: positions in it are from there
    replayed = [json.loads(line) for line in res.stdout.splitlines()]
    again = [(r["slide_id"], r["start"] + base, r["stop"] + base, r["label"], r["reason"]) for r in replayed]
    assert again[: len(live)] == live
    assert any(isinstance(m, Slide) for m in messages)
    assert b"".join(read_chunks(raw))[:2] != b""  # the capture holds what was read


def test_on_sigterm_what_was_read_is_recorded_too(tmp_path: Path) -> None:
    """The reader holds up to ``serial.batch_s`` of bytes (``rest_batch_s`` at rest) before handing them over; stopped, the
    daemon still records (and analyses) them: ``--record`` holds every sample of the ``--raw`` capture."""
    from tactiled.files.recording import load_recording

    config, raw, rec = tmp_path / "c.toml", tmp_path / "cap.bin", tmp_path / "rec.npz"
    config.write_text("[serial]\nbatch_s = 1.0\nrest_batch_s = 1.0\n[publish]\nstatus_interval_s = 0.1\n")
    with board_and_daemon(tmp_path, "--config", str(config), "--raw", str(raw), "--record", str(rec), surfaces=2, seed=3) as live, \
            BlockingSubscriber(live.endpoint, topics=["status"], timeout=20) as sub:
        wait_for(lambda: sub.receive().samples > 20_000, timeout=60, what="a second of samples")  # type: ignore[attr-defined]
        err = live.stop()
    assert live.proc.returncode == 0, err
    ingest = Ingest(2, max_gap=10_000)
    batches = ingest.feed(b"".join(read_chunks(raw))) + ingest.flush()
    recorded = load_recording(rec)
    assert recorded.first_index == batches[0].index
    assert recorded.first_index + recorded.samples.shape[0] == batches[-1].index + batches[-1].samples.shape[0]


def test_end_of_stream_releases_what_the_batcher_held() -> None:
    stream = Stream(Config(), None, max_gap=1000, min_batch=10_000)
    assert stream.feed_bytes(_frames(0, 5)).batches == [] and stream.ingest.held == 100
    assert [b.index for b in stream.finish().batches] == [0]
    assert stream.live.ring.end == 100 and stream.ingest.held == 0
    assert isinstance(Batch(0, np.zeros((3, 2), np.int16)).end, int)


def test_the_watchdog_is_fed_only_while_the_reader_runs(tmp_path: Path) -> None:
    config = Config().override({"publish.endpoint": f"ipc://{tmp_path}/w"})

    async def main() -> tuple[bool, bool, bool]:
        daemon = Daemon(config, None, source_factory=lambda on_bytes, on_state: MemorySource([], on_bytes, on_state))
        try:
            daemon.source = daemon._make_source(None)
            never_ends = asyncio.Event()
            daemon._reader = asyncio.create_task(never_ends.wait())
            now = daemon.source.alive_at
            alive = daemon.reader_alive(now + 1.0)
            stale = daemon.reader_alive(now + 60.0)  # the reader loop stopped ticking (e.g. stuck in an open)
            daemon._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await daemon._reader
            return alive, stale, daemon.reader_alive(now)  # the reader task ended
        finally:
            daemon.publisher.close()

    assert asyncio.run(main()) == (True, False, False)


def test_the_daemon_takes_a_board_reset_past_2_31_between_slides_and_goes_on(tmp_path: Path) -> None:
    """A board reset far ahead (index + 2**31) between slides: the daemon counts a restart, keeps publishing, stays small."""
    sim = simulate_file(SimParams(), pick_surfaces("Ra2.29")[0], 4, 3)
    cut = (sim.truth[1].stop + sim.truth[2].start) // 2 // 20 * 20  # in the rest between the second and third slides
    first = 2**31 + 5000
    data = encode_frames(first, sim.samples[:cut]) + encode_frames((first + cut + 2**31 + 777) % 2**32, sim.samples[cut:])
    master, slave = os.openpty()
    tty.setraw(slave)
    endpoint = f"ipc://{tmp_path}/pub"
    messages: list[object] = []
    with BlockingSubscriber(endpoint, topics=["roughness", "status"], timeout=30) as sub:
        proc = subprocess.Popen(tactiled_cmd("run", "--port", os.ttyname(slave), "--publish", endpoint), stderr=subprocess.PIPE, text=True)
        try:
            wait_for(lambda: messages.append(sub.receive()) or any(isinstance(m, Status) for m in messages),  # type: ignore[func-returns-value]
                     timeout=60, what="the daemon's first status")
            writer = threading.Thread(target=os.write, args=(master, data), daemon=True)  # blocks while the tty is full: paced by the reader
            writer.start()

            def done() -> bool:
                messages.append(sub.receive())
                finals = [m for m in messages if isinstance(m, Roughness) and m.final]
                return len(finals) >= 4 and any(isinstance(m, Status) and m.restarts >= 1 for m in messages[messages.index(finals[-1]):])
            wait_for(done, timeout=120, what="four labels and a status counting the restart after them")
            with open(f"/proc/{proc.pid}/status") as fh:
                rss_kb = next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))
        finally:
            proc.terminate()
            proc.wait(30)
            os.close(master)
            os.close(slave)
    assert proc.returncode == 0
    finals = [m for m in messages if isinstance(m, Roughness) and m.final]
    assert len(finals) == 4 and all(m.label for m in finals)
    assert [m.seq for m in finals] == sorted(m.seq for m in finals) and finals[1].stop < finals[2].start  # the timeline goes on
    assert rss_kb < 300 * 1024, f"peak resident {rss_kb} kB"
