"""A first-day audit's defects, each pinned: record checks the MCAP extra and the model before the port opens, says
when its port gives nothing to record and writes no empty recording, and calls a path that is not a tty what it is;
a paced replay prints each slide as it stands and Ctrl-C keeps what was done; a .bin with no sensor frame is a failed
file; evaluate says when it drew no figures.

The commands run by main() in the test's process (cli_here) where the property is a line, an exit code or a file; the
recorder reads a real pty fed by a thread of the test."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from tactiled.errors import TactiledError
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here, in_thread

# ---- record: everything the end needs is checked before the port opens --------------------------------------------


@pytest.fixture
def no_recording(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """record() replaced by one that notes it was called (and opens no port): the checks must have refused before it."""
    from tactiled.service import recorder

    calls: list[str] = []
    monkeypatch.setattr(recorder, "record", lambda *a, **k: calls.append("record") or pytest.fail("record() was called"))
    return calls


def test_record_mcap_without_the_extra_is_refused_before_the_port_opens(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                         no_recording: list[str], capfd: pytest.CaptureFixture[str]) -> None:
    """Without tactiled[mcap], record --format mcap recorded its seconds, then said the extra was missing (the .npz left)."""
    from tactiled import extras

    real = extras.need

    def need(module: str, extra: str) -> object:
        if module.startswith("mcap"):
            raise TactiledError(f"{module}: not importable (No module named 'mcap'); install it with: pip install 'tactiled[{extra}]'")
        return real(module, extra)

    monkeypatch.setattr(extras, "need", need)
    res = cli_here(capfd, "record", "--port", str(tmp_path / "tty"), "--seconds", "5", "--format", "mcap", "-o", str(tmp_path / "r.mcap"))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "pip install 'tactiled[mcap]'" in lines[0], res.stderr
    assert no_recording == [] and list(tmp_path.iterdir()) == []


def test_record_mcap_with_a_model_that_cannot_load_is_refused_before_the_port_opens(tmp_path: Path, no_recording: list[str],
                                                                                     capfd: pytest.CaptureFixture[str]) -> None:
    model = tmp_path / "nonexist.npz"
    res = cli_here(capfd, "record", "--port", str(tmp_path / "tty"), "--seconds", "4", "--format", "mcap", "--model", str(model),
                   "-o", str(tmp_path / "r.mcap"))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and lines == [f"tactiled: error: {model}: no such model file"], res.stderr
    assert no_recording == [] and list(tmp_path.iterdir()) == []


# ---- record: a port that gives nothing to record ------------------------------------------------------------------


@pytest.fixture
def pty_fed() -> Iterator[Callable[[Callable[[int], bytes]], str]]:
    """A pty whose other end a thread feeds, every 20 ms, with ``chunk(k)`` (the k-th); returns the tty's path."""
    with contextlib.ExitStack() as stack:
        def make(chunk: Callable[[int], bytes]) -> str:
            master, slave = os.openpty()
            os.set_blocking(master, False)  # a full buffer (nobody reading) drops a chunk instead of blocking the feed
            stack.callback(os.close, slave)
            stack.callback(os.close, master)

            def feed(stop: threading.Event) -> None:
                k = 0
                while not stop.wait(0.02):  # the feed's period, not synchronisation
                    data = chunk(k)
                    k += 1
                    with contextlib.suppress(OSError):  # the pty's buffer full: that chunk is dropped
                        os.write(master, data)

            stack.enter_context(in_thread(feed))  # stopped before the pty is closed
            return os.ttyname(slave)

        yield make


def _two_channel_frames(k: int) -> bytes:
    from tactiled.board.frames import encode_frames

    return encode_frames(k * 400, np.full((400, 2), 100, dtype=np.int16))  # 20 ms of a 2-channel board at 20 kHz


@pytest.mark.parametrize("chunk, options, seen", [
    (lambda k: b"", (), "no bytes (is the board on and streaming, and is this its port?)"),
    (lambda k: np.random.default_rng(k).integers(0, 256, 200, dtype=np.uint8).tobytes(), (), "bytes but no valid sensor frame"),
    (_two_channel_frames, ("--channels", "1"), "frames of another channel count skipped (the board sends 2 channels, sensor.channels is 1)"),
], ids=["silent", "noise", "channels"])
def test_record_says_what_its_port_gave_and_writes_no_empty_recording(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                      pty_fed: Callable[[Callable[[int], bytes]], str], chunk: Callable[[int], bytes],
                                                                      options: tuple[str, ...], seen: str, capfd: pytest.CaptureFixture[str]) -> None:
    """A port with no frame: record waited in silence, and Ctrl-C wrote a recording of 0 samples with exit 0 (replacing,
    with --force, a file already there). Now one line after a few seconds naming the port and what it gave, and at the
    stop one line, exit 1, and no file: the one already there stays as it was."""
    from tactiled.service import recorder

    monkeypatch.setattr(recorder, "SILENT_AFTER_S", 1.0)  # 5 s in use
    port = pty_fed(chunk)
    out = tmp_path / "s.npz"
    out.write_bytes(b"an earlier recording")

    class CtrlC(logging.Handler):
        """Ctrl-C once the recorder has said that its port gives nothing to record (its signal handler then stops it)."""

        def emit(self, record: logging.LogRecord) -> None:
            if "nothing to record after" in record.getMessage():
                os.kill(os.getpid(), signal.SIGINT)

    handler = CtrlC()
    recorder.log.addHandler(handler)
    unsaid = threading.Timer(20, os.kill, (os.getpid(), signal.SIGINT))  # never said: Ctrl-C all the same (the test then fails)
    unsaid.start()
    try:
        res = cli_here(capfd, "record", "--port", port, "--seconds", "2", "-o", str(out), "--force", *options)
    finally:
        unsaid.cancel()
        recorder.log.removeHandler(handler)
    lines = res.stderr.strip().splitlines()
    said = [line for line in lines if "nothing to record after" in line]
    assert len(said) == 1 and said[0].startswith(f"tactiled: WARNING: {port}: nothing to record after 1 s: ") and seen in said[0], res.stderr
    assert res.returncode == 1 and lines[-1].startswith(f"tactiled: error: {out}: nothing recorded, no file written: {port}, read for "), res.stderr
    assert seen in lines[-1], lines[-1]
    assert res.stdout == "" and out.read_bytes() == b"an earlier recording" and sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]


def test_record_gives_up_a_port_that_gives_nothing_to_record_after_its_seconds_and_more(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, pty_fed: Callable[[Callable[[int], bytes]], str],
        capfd: pytest.CaptureFixture[str]) -> None:
    """A board of another channel count, nothing to record: --seconds counts sensor time, which never came, so record
    waited until Ctrl-C (an outside audit stopped one after 10 minutes; a script's session hung). It stops after
    --seconds plus GIVE_UP_AFTER_S (30 s in use) of host time: one line, no file, exit 1."""
    from tactiled.service import recorder

    monkeypatch.setattr(recorder, "SILENT_AFTER_S", 0.5)
    monkeypatch.setattr(recorder, "GIVE_UP_AFTER_S", 1.0)
    port = pty_fed(_two_channel_frames)
    out = tmp_path / "s.npz"
    res = cli_here(capfd, "record", "--port", port, "--seconds", "0.5", "-o", str(out), "--channels", "1")
    lines = res.stderr.strip().splitlines()
    assert any(re.search(r"still waiting, at most \d+ s more \(Ctrl-C stops\)", line) for line in lines), res.stderr
    assert any(re.search(rf"{re.escape(port)}: nothing to record after \d+ s \(--seconds 0.5 and 1 s more\): stopping", line)
               for line in lines), res.stderr
    assert res.returncode == 1 and lines[-1].startswith(f"tactiled: error: {out}: nothing recorded, no file written"), res.stderr
    assert not out.exists()


# ---- a path that is not a tty -------------------------------------------------------------------------------------


def test_record_on_a_file_that_is_not_a_tty_says_so(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """pyserial's own words were shown: "Could not configure port: (25, 'Inappropriate ioctl for device')"."""
    path = tmp_path / "notatty.txt"
    path.write_text("hello\n")
    res = cli_here(capfd, "record", "--port", str(path), "--seconds", "1", "-o", str(tmp_path / "r.npz"))
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        f"tactiled: error: {path}: not a serial port (a tty): a regular file of 6 bytes"], res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notatty.txt"]


def test_the_daemons_reader_retries_a_path_that_is_not_a_tty_and_says_it_plainly(tmp_path: Path) -> None:
    """run keeps retrying (a device may yet appear there); its log line says what the path is, as record does."""
    from tactiled.board.serialsource import DISCONNECTED, SerialSource, open_error

    path = tmp_path / "notatty.txt"
    path.write_text("hello\n")
    states: list[tuple[str, str]] = []
    said = threading.Event()
    source = SerialSource(str(path), lambda data: None, lambda state, detail: states.append((state, detail)) or said.set(), retry_max_s=0.05)
    source.start()
    try:
        assert said.wait(10)
    finally:
        source.stop()
    assert states[0] == (DISCONNECTED, "cannot open: not a serial port (a tty): a regular file of 6 bytes; retrying"), states
    # a character device that is no terminal: pyserial's configure error, said the same way
    configure = OSError("Could not configure port: (25, 'Inappropriate ioctl for device')")
    assert open_error(configure) == "not a serial port (a tty): a character device that is not a terminal"


# ---- replay ---------------------------------------------------------------------------------------------------------


def test_a_bin_with_no_sensor_frame_is_a_failed_file_and_the_others_still_play(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """An empty file, a TOML file and random bytes named .bin replayed as captures of 0 slides, exit 0."""
    from tactiled.files.capture import recording_bytes
    from tactiled.files.recording import load_recording, save_recording
    from tests.conftest import lossy_recording

    empty, toml, noise, good = (tmp_path / n for n in ("empty.bin", "config.bin", "noise.bin", "good.bin"))
    empty.write_bytes(b"")
    toml.write_text("[sensor]\nport = \"/dev/ttyACM0\"\n")
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes())
    save_recording(tmp_path / "r.npz", lossy_recording(0, lost=()))
    good.write_bytes(recording_bytes(load_recording(tmp_path / "r.npz")))
    res = cli_here(capfd, "replay", "--jobs", "1", *map(str, (empty, toml, good, noise)))
    errors = res.stderr.strip().splitlines()
    assert res.returncode == 2 and errors == [
        f"tactiled: error: {empty}: no sensor frame in 0 bytes: an empty file",
        f"tactiled: error: {toml}: no sensor frame in {toml.stat().st_size} bytes: not a raw capture of the sensor's port",
        f"tactiled: error: {noise}: no sensor frame in 100000 bytes: not a raw capture of the sensor's port",
    ], res.stderr
    assert f"{good}: 3 slides" in res.stdout and str(empty) not in res.stdout, res.stdout


@pytest.fixture(scope="module")
def fluctuating(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of slides whose force dips: ends said after a short quiet, then withdrawn (the slide went on)."""
    root = tmp_path_factory.mktemp("fluctuating")
    return Path(write_dataset(root, scene="fluctuating", surfaces="Ra0.44", files_per_surface=1, slides_per_file=8, seed=3)[0])


class _Watched:
    """Pacer (patched into replay_files) that notes the newest index it was asked to wait for, never waits, and raises
    KeyboardInterrupt (Ctrl-C) once asked for ``stop_at`` (relative to the first index) or beyond."""

    stop_at: int | None = None
    reached = 0

    @classmethod
    def make(cls) -> type:
        from tactiled.run.pacer import Pacer

        watched = cls

        class Watched(Pacer):
            def wait(self, index: int) -> None:
                first = self._origin(index)
                watched.reached = index - first
                if watched.stop_at is not None and index - first >= watched.stop_at:
                    raise KeyboardInterrupt
        return Watched


def test_a_paced_replay_hands_each_slide_over_as_it_stands(fluctuating: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """replay --speed printed nothing until the file had played. Each slide now comes once its final result stands
    (after the quiet that makes its end certain, withdrawn ends never shown), the same slides and provisional results,
    in the same order, as the whole file's replay gives."""
    from tactiled.config import load_config
    from tactiled.core.events import SlideResumed
    from tactiled.files.recording import load_recording
    from tactiled.learn.choose import ModelChoice
    from tactiled.run.replay import by_slide, replay_recording
    from tactiled.service import replay_files as rf

    config = load_config(None)
    rec = load_recording(fluctuating)
    events: list[object] = []
    replay_recording(rec, config, ModelChoice(config).for_stream(rec.fs, rec.channels, "r"), on_event=events.append)
    assert sum(isinstance(e, SlideResumed) for e in events) >= 2  # the case that makes waiting for a final to stand matter
    monkeypatch.setattr(_Watched, "stop_at", None)
    monkeypatch.setattr(rf, "Pacer", _Watched.make())
    settle = round(config.detector.off_hold_s * rec.fs)
    shown: list[tuple[object, object, int]] = []
    for block in (800, 7777):
        shown.clear()
        played = list(rf.replay_files([str(fluctuating)], config, ModelChoice(config), block=block, speed=1e9,
                                      on_slide=lambda path, r, final, provisional, model: shown.append((final, provisional, _Watched.reached))))
        assert [(f, p) for f, p, _ in shown] == by_slide(played[0].results) and len(shown) == 8
        for final, _, at in shown:  # at: the block being played when it was shown
            assert final.stop + settle <= at + block and at <= final.stop + settle + 2 * block, (block, final.stop, at)  # type: ignore[attr-defined]


@pytest.mark.parametrize("json_out", [False, True], ids=["lines", "json"])
def test_ctrl_c_in_a_paced_replay_keeps_what_was_done(fluctuating: Path, monkeypatch: pytest.MonkeyPatch, json_out: bool,
                                                       capfd: pytest.CaptureFixture[str]) -> None:
    """Ctrl-C in replay --speed 1 printed only ^C, exit 1, though slides had been analysed. Now the slides that stood,
    then the file's summary so far, exit 1 (a command interrupted); the next file is not played."""
    import json

    from tactiled.service import replay_files as rf

    monkeypatch.setattr(_Watched, "stop_at", 260_000)  # 13 s of 25.9
    monkeypatch.setattr(rf, "Pacer", _Watched.make())
    res = cli_here(capfd, "replay", "--speed", "1", *(["--json"] if json_out else []), str(fluctuating), str(fluctuating))
    assert res.returncode == 1, res.stderr
    if json_out:
        slides = [json.loads(line) for line in res.stdout.splitlines()]
        stops = [s["stop"] for s in slides]
        summary = res.stderr.strip().splitlines()[-1]
    else:
        *lines, summary = res.stdout.strip().splitlines()
        stops = [int(line.split(": ")[2].split("-")[1].split(" ")[0]) for line in lines]
    assert len(stops) >= 3 and all(stop < 260_000 for stop in stops), res.stdout
    total = np.load(fluctuating)["samples"].shape[0] / 20_000
    assert summary.startswith(f"{fluctuating}: interrupted at 13.0 s of {total:.1f} s: {len(stops)} slides, "), summary
    assert summary.endswith("true slides right (those ended by then)"), summary
    assert res.stdout.count(str(fluctuating)) == len(stops) + (0 if json_out else 1)  # the second file was not played


def test_a_paced_replays_blocks_are_about_40_ms_of_wall_time() -> None:
    from tactiled.service.replay_files import paced_block

    assert paced_block(20_000.0, 1.0) == 800 and paced_block(20_000.0, 4.0) == 3200 and paced_block(20_000.0, 2.5) == 2400
    assert paced_block(20_000.0, 1e6) <= 65536 and paced_block(20_000.0, 0.1) == 800


# ---- evaluate without matplotlib ------------------------------------------------------------------------------------


def test_evaluate_without_matplotlib_says_the_figures_were_not_drawn(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capfd: pytest.CaptureFixture[str]) -> None:
    """write_figures returned [] without a word: the report had no figures and said nothing of why."""
    import sys

    from tactiled.learn.evaluate import Evaluator

    for name in ("matplotlib", "matplotlib.pyplot"):
        monkeypatch.setitem(sys.modules, name, None)  # import raises ImportError, as without the report extra
    monkeypatch.setattr(Evaluator, "window_grid", lambda self, starts, durations: [])  # (f) has a figure; its run is not the point
    files = [str(p) for p in write_dataset(tmp_path / "d", scene="robot", surfaces="2", files_per_surface=2, slides_per_file=1)]
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *files, "--report", str(report), "--quick", "--experiments", "f", "--folds", "2")
    assert res.returncode == 0, res.stderr
    note = "figures not drawn: matplotlib is not installed; to get them: pip install 'tactiled[report]'"
    assert [line for line in res.stderr.splitlines() if "figures" in line] == [f"evaluate: {note}"], res.stderr
    assert f"F{note[1:]}." in (report / "report.md").read_text() and not list(report.glob("*.png"))
