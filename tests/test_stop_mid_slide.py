"""SIGTERM while the finger slides: the slide under way ends at the last sample read (reason ``end_of_stream``, as its
recording's replay ends it at the file's end) and gets its final label; the subscriber receives it and then the
stopping status before the daemon's sockets close.

A real virtual board on a pty, ``tactiled run`` as a process, a client subscriber on an ipc socket.
"""

from __future__ import annotations

from pathlib import Path

from tactiled_client import BlockingSubscriber, NoData, Roughness, Slide, Status, schema

from tactiled.config import Config
from tactiled.files.recording import load_recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording
from tactiled.sim.physics import SimParams
from tests.conftest import board_and_daemon, wait_for


def test_a_stop_during_a_slide_ends_it_with_its_final_label_as_its_recording_replays(tmp_path: Path) -> None:
    messages: list[object] = []
    with board_and_daemon(tmp_path, "--record", str(tmp_path / "got.npz"), params=SimParams(mode="robot"), seed=3) as live, \
            BlockingSubscriber(live.endpoint, timeout=20) as sub:

        def sliding() -> bool:  # a slide has begun after a first labelled one, and is still under way
            messages.append(sub.receive())
            m = messages[-1]
            ended = {s.slide_id for s in messages if isinstance(s, Slide) and s.event == schema.SLIDE_END}
            return isinstance(m, Roughness) and not m.final and bool(ended) and m.slide_id not in ended

        wait_for(sliding, timeout=120, what="a provisional label of a slide under way, after a first slide ended")
        open_id = messages[-1].slide_id  # type: ignore[attr-defined]
        live.proc.terminate()
        try:
            while not (isinstance(messages[-1], Status) and messages[-1].state == schema.STATE_STOPPING):
                messages.append(sub.receive(timeout=10))
        except NoData:
            pass
        live.proc.wait(30)
    assert live.proc.returncode == 0
    assert isinstance(messages[-1], Status) and messages[-1].state == schema.STATE_STOPPING, "no stopping status received"
    end = [m for m in messages if isinstance(m, Slide) and m.slide_id == open_id and m.event == schema.SLIDE_END]
    final = [m for m in messages if isinstance(m, Roughness) and m.slide_id == open_id and m.final]
    assert len(end) == 1 and end[0].reason == "end_of_stream"
    assert len(final) == 1 and messages.index(final[0]) > messages.index(end[0]) and final[0].label is not None
    # the recording ends with the last sample read: its replay ends that slide there too (where a quiet that began before
    # the stop began, when the finger was already lifting: the end of a slide as its detector always places it), same label
    got = load_recording(tmp_path / "got.npz")
    assert end[0].stop <= got.first_index + got.samples.shape[0]
    last = [r for r in replay_recording(got, Config(), load_model()) if r.final][-1]
    assert (last.start + got.first_index, last.stop + got.first_index, last.label) == (final[0].start, final[0].stop, final[0].label)
