"""How often the daemon's loop is handed bytes: the serial source's hand-over period can change while it reads, the daemon
lengthens it while no slide can be in progress, and analyses a window on the loop while the model's analysis is cheap."""

from __future__ import annotations

import asyncio
import os
import threading
import tty
from collections.abc import Callable
from typing import Any

import pytest

import tactiled.service.daemon as daemon_module
from tactiled.board.serialsource import CONNECTED, SerialSource
from tactiled.config import Config
from tactiled.learn.model import load_model
from tactiled.run.stream import Stream
from tactiled.service.daemon import Daemon
from tests.conftest import memory_daemon
from tests.test_ingest import _stream


def test_the_hand_over_period_changes_while_the_source_reads() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    got: list[bytes] = []

    async def main() -> None:
        arrived, opened = asyncio.Event(), asyncio.Event()
        reads = [threading.Event(), threading.Event()]  # set by the reader thread as it reads the first and second write

        class Tee:  # the raw-capture hook: called in the reader thread for every read, before the hand-over check
            def write(self, data: bytes) -> None:
                for r in reads:
                    if not r.is_set():
                        r.set()
                        return

            def flush(self) -> None:
                pass

        def on_bytes(data: bytes) -> None:
            got.append(data)
            arrived.set()

        def on_state(state: str, detail: str) -> None:
            if state == CONNECTED:
                opened.set()

        source = SerialSource(os.ttyname(slave), on_bytes, on_state, read_interval_s=0.005, hand_over_s=3600.0, tee=Tee())  # type: ignore[arg-type]
        task = asyncio.create_task(source.run())
        await asyncio.wait_for(opened.wait(), 20)  # bytes written before the port is open would be discarded as stale
        for i, read in enumerate(reads):
            os.write(master, b"x" * 50)
            assert await asyncio.to_thread(read.wait, 20), f"the reader never read write {i + 1}"
        # the first read's hand-over check has passed; a hand-over would have reached the loop before this wake-up
        assert not got  # read, but held: the hour-long hand-over period has not passed
        source.hand_over_s = 0.0  # the consumer shortens it: what is held goes at the next read
        await asyncio.wait_for(arrived.wait(), 20)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    try:
        asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert b"".join(got) == b"x" * 100


def _run_daemon(config: Config, chunk: int, probe: Callable[[Daemon], None]) -> Daemon:
    """The daemon on a memory source of a few seconds of slides, ``probe(daemon)`` called after each chunk it consumed."""
    data, _ = _stream(seed=6)
    daemon: Daemon = memory_daemon(config, load_model(), data, chunk, probe)
    asyncio.run(daemon.run())
    return daemon


def test_the_daemon_is_handed_bytes_less_often_while_no_slide_can_be_in_progress(tmp_path: Any) -> None:
    config = Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub", "serial.batch_s": 0.04, "serial.rest_batch_s": 0.25})
    seen: list[tuple[bool, bool, float]] = []

    def probe(d: Daemon) -> None:
        assert d.source is not None
        seen.append((d.pipeline.sliding, d.pipeline.detector.undecided, d.source.hand_over_s))

    daemon = _run_daemon(config, 920, probe)
    assert daemon.pipeline.slides >= 1
    assert {h for sliding, undecided, h in seen if sliding or undecided} == {0.04}  # a slide may be under way: the batch
    assert {h for sliding, undecided, h in seen if not (sliding or undecided)} == {0.25}  # at rest: the longer period
    assert any(s for s, _, _ in seen) and any(not (s or u) for s, u, _ in seen)
    # never shorter than the batch: a rest period below it means the batch
    short = Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub2", "serial.batch_s": 0.04, "serial.rest_batch_s": 0.0})
    periods: set[float] = set()
    _run_daemon(short, 920, lambda d: periods.add(d.source.hand_over_s) if d.source is not None else None)
    assert periods == {0.04}


@pytest.mark.parametrize("inline_below_s", [3600.0, 0.0])
def test_a_window_is_analysed_on_the_loop_only_while_analysis_is_cheap(tmp_path: Any, monkeypatch: pytest.MonkeyPatch,
                                                                        inline_below_s: float) -> None:
    """The first window goes to a worker thread (its cost is unknown); the next ones run on the loop while the last took at
    most INLINE_ANALYSIS_S, in the thread otherwise; the events are the same either way (the memory-source test checks them)."""
    monkeypatch.setattr(daemon_module, "INLINE_ANALYSIS_S", inline_below_s)
    hops = 0
    to_thread = asyncio.to_thread

    async def counting(fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        nonlocal hops
        hops += getattr(fn, "__name__", "") == "process"
        return await to_thread(fn, *args, **kwargs)

    monkeypatch.setattr(daemon_module.asyncio, "to_thread", counting)
    windows = 0
    will_analyse = Stream.will_analyse

    def counting_windows(self: Stream, end: int) -> bool:
        nonlocal windows
        ahead = will_analyse(self, end)
        windows += ahead
        return ahead

    monkeypatch.setattr(Stream, "will_analyse", counting_windows)
    daemon = _run_daemon(Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub"}), 920, lambda d: None)
    assert daemon.pipeline.slides >= 1 and windows >= 3
    assert hops == (1 if inline_below_s else windows)  # cheap: the first in the thread, then on the loop; else all in the thread


def test_bytes_read_just_before_the_port_fails_in_the_same_read_are_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    """A USB serial device unplugged between two reads of one drain (a tty hands out at most ~4 kB a read) raises EIO on the
    second: the first read's bytes were dropped with the exception. They are returned now, and the next drain meets the error."""
    import types

    import tactiled.board.serialsource as serialsource

    chunks: list[bytes | OSError] = [b"a" * 4095, b"b" * 100, OSError(5, "Input/output error"), OSError(5, "Input/output error")]

    def readv(fd: int, buffers: list[memoryview]) -> int:
        item = chunks.pop(0)
        if isinstance(item, OSError):
            raise item
        buffers[0][:len(item)] = item
        return len(item)

    monkeypatch.setattr(serialsource, "os", types.SimpleNamespace(readv=readv))
    buf = bytearray(1 << 16)
    assert serialsource._read_all(3, 1 << 16, buf) == b"a" * 4095 + b"b" * 100
    with pytest.raises(OSError):
        serialsource._read_all(3, 1 << 16, buf)
