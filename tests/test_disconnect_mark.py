"""A recording marks where the host lost the sensor's port (its ``disconnected`` key), so that its replay ends a slide
there as the live daemon did: written by ``run --record`` and ``record`` through the journal, kept by ``recover``,
checked at load."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactiled.board.serialsource import CONNECTED, DISCONNECTED, SerialSource
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideEnded, SlideResult
from tactiled.errors import RecordingError
from tactiled.files.journal import DISCONNECTED_KEY, JournalWriter, encode_chunk, encode_header, journal_path
from tactiled.files.recording import Recording, load_recording, save_recording
from tactiled.learn.model import load_model
from tactiled.run.ingest import Batch
from tactiled.run.replay import replay_recording
from tactiled.service.daemon import Daemon
from tactiled.service.recorder import RecordingSink
from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
from tactiled.sim.virtualboard import VirtualBoard
from tests.conftest import in_thread

FS = 20_000


def _key(ev: PipelineEvent) -> tuple[Any, ...]:
    """What a subscriber sees of a pipeline event (no timings, no features)."""
    if isinstance(ev, SlideResult):
        return ("result", ev.slide_id, ev.start, ev.stop, ev.window, ev.label, ev.reason, ev.confidence, ev.final, ev.novelty)
    return (type(ev).__name__, *dataclasses.astuple(ev))


def _board(tmp_path: Path, unplug_at: float, rest_s: float = 0.8, slide_s: float = 1.6) -> VirtualBoard:
    """A virtual board on ``tmp_path/tty`` (opened, not yet streaming) at 3x real time: ``rest_s`` at rest (0: the stream
    begins in the slide), a ``slide_s`` slide, then rest; unplugged for 0.1 s at ``unplug_at`` s of sensor time (shorter
    than detector.off_hold_s: without a mark, a replay would join the slide's two pieces)."""
    sim = SensorSimulator(SimParams(), seed=3)
    surface = pick_surfaces("Ra2.29")[0]
    if rest_s:
        sim.add_rest(rest_s)
    sim.add_slide(surface, slide_s)
    sim.add_rest(3.0)
    board = VirtualBoard(sim, [surface], link=str(tmp_path / "tty"), speed=3.0, unplug_at=[unplug_at], unplug_s=0.1, seed=3,
                         log=open(tmp_path / "board.jsonl", "w"))  # noqa: SIM115 - closed with the board's thread (streams)
    board.open()
    return board


@pytest.mark.parametrize("rest_s, slide_s, unplug_at", [(0.8, 1.6, 1.6), (0.0, 2.0, 1.0)], ids=["from-rest", "began-in-the-slide"])
def test_run_record_marks_the_unplug_and_its_replay_gives_the_live_daemons_events(tmp_path: Path, rest_s: float, slide_s: float,
                                                                                   unplug_at: float) -> None:
    """The live daemon ends the slide the unplug cuts (reason disconnected, with its label) and starts another after the
    replug; its recording marks the unplug, and a replay of it gives every event the daemon gave (the pieces not joined).
    The board is closed after 3 s of sensor time: a second disconnection, marked at the recording's end, stops the daemon.
    The same when the daemon connects while the finger already slides (``began-in-the-slide``: the detector has not yet
    told the stream's level from rest; the stream so far ends as one slide, and the one after the replug starts afresh)."""
    board = _board(tmp_path, unplug_at=unplug_at, rest_s=rest_s, slide_s=slide_s)
    out = tmp_path / "live.npz"
    config = Config().override({"sensor.port": board.link or "", "publish.endpoint": f"ipc://{tmp_path}/pub"})
    model = load_model()
    connected = threading.Event()
    seen: list[PipelineEvent] = []

    class Watched(Daemon):
        disconnects = 0

        def _publish(self, events: list[PipelineEvent], detected_at: float, overloaded: bool = False) -> None:
            seen.extend(events)
            super()._publish(events, detected_at, overloaded)

        def _on_state(self, state: str, detail: str) -> None:
            super()._on_state(state, detail)
            if state == CONNECTED:
                connected.set()
            elif state == DISCONNECTED:
                self.disconnects += 1
                if self.disconnects == 2:  # the board closed for good: stop (what was read is recorded)
                    self.stop_event.set()

    def stream(stop: threading.Event) -> None:
        if connected.wait(20):  # the daemon holds the port: no byte is stale
            board.run(stop, seconds=3.0)
        board.remove_link()
        board.close()
        assert board.log is not None
        board.log.close()

    daemon = Watched(config, model, record_to=str(out))

    async def main() -> None:
        await asyncio.wait_for(daemon.run(), 30)

    with in_thread(stream):
        asyncio.run(main())
    assert daemon.recording_error is None and not daemon.state.overloaded
    ends = [e for e in seen if isinstance(e, SlideEnded)]
    last = {e.slide_id: e.reason for e in ends}  # a slide's last end (on a loaded machine the board may overrun: a gap in
    assert list(last.values()) == ["disconnected", "quiet"], ends  # the second slide is a dip, an end withdrawn and made again)
    cut = ends[0]
    assert cut.reason == "disconnected", ends
    assert any(isinstance(e, SlideResult) and e.final and e.slide_id == cut.slide_id and e.quality["windows"] >= 1 for e in seen)

    rec = load_recording(out)
    n = rec.samples.shape[0]
    mark = int(rec.disconnected[0])
    assert rec.disconnected.tolist() == [mark, n], rec.disconnected
    assert cut.stop <= rec.first_index + mark and mark in rec.lost[:, 0], (cut, mark, rec.lost)  # the unplug's samples follow it
    replayed: list[PipelineEvent] = []
    replay_recording(rec, config, model, on_event=replayed.append)
    assert [_key(e) for e in replayed] == [_key(e) for e in seen]


def test_record_marks_the_unplug_after_the_rows_read_before_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``tactiled record`` (in this process): the port's loss reaches the recorder on the reader thread, while bytes read
    before it may still wait in its queue; the mark is placed after them, where the unplug's gap begins."""
    import tactiled.service.recorder as recorder

    board = _board(tmp_path, unplug_at=0.5)
    connected = threading.Event()

    class Signalling(SerialSource):  # the recorder's source, saying when it holds the port (the board then starts)
        def __init__(self, path: str, on_bytes: Any, on_state: Any, **kw: Any) -> None:
            def state(s: str, detail: str) -> None:
                on_state(s, detail)
                if s == CONNECTED:
                    connected.set()
            super().__init__(path, on_bytes, state, **kw)

    monkeypatch.setattr(recorder, "SerialSource", Signalling)

    def stream(stop: threading.Event) -> None:
        if connected.wait(20):
            board.run(stop)
        board.close()
        assert board.log is not None
        board.log.close()

    with in_thread(stream):
        summary = recorder.record(Config().override({"sensor.port": board.link or ""}), 0.8, tmp_path / "r.npz")
    assert summary.error is None and summary.reconnects == 1
    rec = load_recording(tmp_path / "r.npz")
    assert rec.disconnected.shape == (1,) and rec.disconnected[0] in rec.lost[:, 0], (rec.disconnected, rec.lost)  # the gap follows


@pytest.mark.parametrize(("marks", "problem"), [
    (np.array([1.0, 2.0]), "must be (d,) integers"),
    (np.array([[1, 2]]), "must be (d,) integers"),
    (np.array([-1, 3]), "positions outside samples (0..10)"),
    (np.array([3, 11]), "positions outside samples (0..10)"),
    (np.array([3, 3]), "strictly increasing"),
    (np.array([5, 3]), "strictly increasing"),
])
def test_a_malformed_disconnected_key_is_refused_in_one_line(tmp_path: Path, marks: np.ndarray, problem: str) -> None:
    path = tmp_path / "bad.npz"
    np.savez(path, samples=np.zeros((10, 2), dtype=np.int16), fs=np.float64(FS), disconnected=marks)
    with pytest.raises(RecordingError) as err:
        load_recording(path)
    assert str(err.value).startswith(f"{path}: disconnected: ") and problem in str(err.value) and "\n" not in str(err.value), err.value


def test_marks_round_trip_and_a_file_without_any_has_no_such_member(tmp_path: Path) -> None:
    import zipfile

    rec = Recording(np.zeros((10, 2), dtype=np.int16), float(FS), disconnected=np.array([0, 4, 10]))
    save_recording(tmp_path / "m.npz", rec)
    assert load_recording(tmp_path / "m.npz").disconnected.tolist() == [0, 4, 10]
    save_recording(tmp_path / "none.npz", Recording(np.zeros((10, 2), dtype=np.int16), float(FS)))
    assert "disconnected.npy" not in zipfile.ZipFile(tmp_path / "none.npz").namelist()
    assert load_recording(tmp_path / "none.npz").disconnected.tolist() == []


def test_the_sinks_marks_go_through_the_journal_once_each(tmp_path: Path) -> None:
    """Marks at a position with no rows since the last collapse to one; none before the first row; a mark after the last
    row is kept too (a chunk of no rows may carry it)."""
    rows = np.arange(200, dtype=np.int16).reshape(100, 2)
    sink = RecordingSink(tmp_path / "s.npz", fs=float(FS), channels=2, volts_per_count=1.0)
    sink.mark_disconnected()  # the port absent at the start: nothing to mark
    sink.add(Batch(1000, rows[:50]))
    sink.mark_disconnected()
    sink.mark_disconnected()  # reported again before any row came
    sink.add(Batch(1070, rows[50:]))  # back 20 samples later
    sink.mark_disconnected()
    assert sink.finish().error is None
    rec = load_recording(tmp_path / "s.npz")
    assert rec.disconnected.tolist() == [50, 120] and rec.lost.tolist() == [[50, 20]] and rec.first_index == 1000
    assert DISCONNECTED_KEY not in rec.meta


def test_recover_keeps_the_marks_of_a_killed_recorders_journal(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A journal as a killed recorder leaves it: a mark inside a chunk, one in a chunk of no rows after the last, and a torn
    chunk at the end; ``tactiled recover`` keeps both marks and never puts them in meta."""
    from tactiled.cli.main import main

    rows = np.arange(400, dtype=np.int16).reshape(200, 2)
    journal = journal_path(tmp_path / "k.npz")
    writer = JournalWriter(journal, encode_header(float(FS), 2, 1.0, None, {}))
    writer.append(encode_chunk(0, 500, 130, [(80, 30)], {"crc_errors": 0}, rows[:100], [80]))
    writer.append(encode_chunk(130, 630, 100, [], {"crc_errors": 1}, rows[100:], [230]))
    writer.append(encode_chunk(230, 730, 0, [], {"crc_errors": 1}, rows[:0], [230]))
    torn = encode_chunk(230, 730, 10, [], {"crc_errors": 1}, rows[:10], [240])
    writer.append(torn[: len(torn) // 2])
    writer.close()
    assert main(["recover", str(journal), "-o", str(tmp_path / "k.npz")]) == 0, capsys.readouterr().err
    rec = load_recording(tmp_path / "k.npz")
    assert rec.disconnected.tolist() == [80, 230] and rec.lost.tolist() == [[80, 30]] and rec.samples.shape[0] == 230
    assert rec.meta["crc_errors"] == 1 and DISCONNECTED_KEY not in rec.meta
