"""The monitor, headless: a real daemon on a virtual board's pty, its messages rendered by rich to a string."""

from __future__ import annotations

import io
from pathlib import Path

from rich.console import Console
from tactiled_client import BlockingSubscriber, Roughness

from tactiled.apps.monitor import SPARK, MonitorState, render
from tests.conftest import board_and_daemon, wait_for


def test_monitor_shows_state_traces_spectrum_and_labels_with_truth(tmp_path: Path) -> None:
    model = MonitorState(str(tmp_path / "board.jsonl"))
    with board_and_daemon(tmp_path, "--samples", surfaces=4, seed=4, drop=0.01) as live, BlockingSubscriber(live.endpoint, timeout=30) as sub:
        def enough() -> bool:
            model.update(sub.receive())
            finals = [r for r in model.labels if r.final and r.label]
            return len(finals) >= 2 and model.status is not None and model.raw_n >= 4096
        wait_for(enough, timeout=120, what="two labels, a status and raw samples")
    endpoint = live.endpoint
    console = Console(file=io.StringIO(), width=140, record=True, color_system=None)
    console.print(render(model, endpoint))
    screen = console.export_text()
    assert "sensor fingertip0" in screen and any(state in screen for state in (" IDLE ", " SLIDING "))
    for header in ("film levels (RMS per 10 ms, mV)", "now, mV", "trace (newest right)", "spectrum of the raw samples", "Hz per column",
                   "slide", "kind", "label", "confidence", "used, s", "duration, s", "latency, ms", "truth", "abstained: reason"):
        assert header in screen, header
    traces = [line for line in screen.splitlines() if line.strip().startswith(("│ film1", "│ film2", "film1", "film2"))]
    assert len(traces) == 2 and all(sum(ch in SPARK for ch in line) >= 50 for line in traces)  # moving traces of both films
    assert sum(ch in SPARK for ch in screen.split("spectrum of the raw samples")[1].split("Hz per column")[0]) >= 40  # spectrum bars
    finals = [r for r in model.labels if r.final and r.label]
    truths = [model.truth_for(r.start, r.stop) for r in finals]
    assert all(truths) and all(t in screen for t in truths)  # the simulator's true surface of each labelled slide
    assert all(r.label in screen for r in finals) and isinstance(finals[0], Roughness)
    small = Console(file=io.StringIO(), width=80, height=24, record=True, color_system=None)
    small.print(render(model, endpoint, 80, 24))
    lines = small.export_text().rstrip("\n").splitlines()
    assert len(lines) <= 24 and max(len(line) for line in lines) <= 80  # fits 80×24 without wrapping
    text = "\n".join(lines)
    assert any(state in text for state in (" IDLE ", " SLIDING ")) and "lost " in text and "crc " in text
    films = [line for line in lines if line.startswith(("film1 ", "film2 "))]
    assert len(films) == 2 and all(sum(ch in SPARK for ch in line) >= 40 for line in films)
    assert all(r.label in text for r in finals[:5])  # the last labels are on screen


def test_monitor_highlights_abstentions_and_provisional_labels() -> None:
    from tactiled_client import schema

    from tactiled.core.events import SlideResult

    model = MonitorState()
    model.update(schema.status("s", state=schema.STATE_DISCONNECTED, fs_nominal=20_000.0, discarded_at_start=68_040, channel_errors=300))
    for final, label, reason in ((False, "Ra1.00", None), (True, None, "samples_lost")):
        r = SlideResult(1, 0, 20_000, (6000, 16_000), label, reason, 0.4, [], {}, final=final, used_s=0.5)
        model.update(schema.roughness("s", r, fs=20_000.0, model="m", version="t"))
    console = Console(file=io.StringIO(), width=140, record=True, force_terminal=True, color_system="standard")
    console.print(render(model, "ipc://x"))
    text = console.export_text(clear=False)
    assert " DISCONNECTED " in text and "provisional" in text and "samples_lost" in text and "(waiting for raw samples)" in text
    assert "discarded at start 68040 bytes" in text and "300 frames of another channel count skipped" in text
    styled = console.export_text(styles=True)
    assert "\x1b[1;31m" in styled  # bold red: the abstention and the disconnected state
    small = Console(file=io.StringIO(), width=80, height=24, record=True, color_system=None)
    small.print(render(model, "ipc://x", 80, 24))
    lines = small.export_text().rstrip("\n").splitlines()
    assert len(lines) <= 24 and max(len(line) for line in lines) <= 80
    assert " DISCONNECTED " in lines[1] and any("samples_lost" in line for line in lines) and any("prov." in line for line in lines)
    assert lines[3].startswith("discarded at start 68040 bytes") and "…" not in lines[3]
    assert lines[4].startswith("300 frames of another channel count skipped")


def test_the_rate_shown_is_the_clock_maps_not_one_intervals_count() -> None:
    """At rest the daemon hands samples over every 0.2 s, so the samples counted in one 0.5 s status interval swing
    (12 000 to 27 000 Hz on a steady 20 kHz board, seen by an audit): the monitor leads with the clock map's rate."""
    from tactiled_client import schema

    from tactiled.apps.monitor import rate

    model = MonitorState()
    steady = schema.status("s", fs_nominal=20_000.0, fs_measured=11_928.0, fs_clock=20_000.4)
    assert rate(model, steady, full=False) == "20000 Hz"
    assert rate(model, steady, full=True) == "rate 20000.4 Hz (last interval 11928 Hz, nominal 20000 Hz)"
    unready = schema.status("s", fs_nominal=20_000.0, fs_measured=19_950.0, fs_clock=0.0)  # the map not ready yet
    assert rate(model, unready, full=False) == "19950 Hz"
