"""Defects an audit found in swapping models live (SIGHUP, control ``load``, a shadow model), each pinned by a check.

In the test's process: a daemon fed from memory (tactiled.board.serialsource.MemorySource), its messages taken from the
publisher as they are sent, and a loader that waits on an event the test sets where the order of two loads matters.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from tactiled_client import Roughness, Shadow, Slide, schema

import tactiled.service.daemon as daemon_module
from tactiled.board.frames import encode_frames
from tactiled.board.serialsource import MemorySource
from tactiled.config import Config
from tactiled.learn.model import Model, load_model
from tactiled.service.daemon import Daemon
from tests.conftest import memory_daemon

FS = 20_000


def _model(path: Path, note: str, **settings: float) -> tuple[Model, str]:
    """The shipped model under another fingerprint (``note`` in its summary; ``settings`` changed), saved at ``path``."""
    model = load_model()
    model.summary = {**model.summary, "note": note}
    if settings:
        model.settings = replace(model.settings, **settings)
    return model, model.save(path)


def _config(tmp_path: Path) -> Config:
    return Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub"})


@pytest.mark.parametrize("first", ["control", "SIGHUP"])
def test_the_last_load_requested_wins_over_an_earlier_one_still_being_checked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                              caplog: pytest.LogCaptureFixture, first: str) -> None:
    """A control load of a slow file, then SIGHUP (or the other way round): the audit's daemon swapped in whichever finished
    loading last (the slow one), so a reload did not load model.path as promised. The first request's load is held until
    the second's has been swapped in; then it is not swapped in, and its reply (or line) says so in one line."""
    _, slow = _model(tmp_path / "slow.npz", "slow to load")
    _, fast = _model(tmp_path / "fast.npz", "quick to load")
    model_path = tmp_path / ("slow.npz" if first == "SIGHUP" else "fast.npz")  # what SIGHUP loads
    other = tmp_path / ("fast.npz" if first == "SIGHUP" else "slow.npz")  # what control loads
    entered, release = threading.Event(), threading.Event()
    real = daemon_module.load_model

    def loader(path: str | Path | None = None) -> Model:
        if path is not None and Path(path).name == "slow.npz":
            entered.set()
            assert release.wait(30), "the slow load was never released"
        return real(path)

    monkeypatch.setattr(daemon_module, "load_model", loader)
    caplog.set_level(logging.INFO, logger="tactiled.service.daemon")

    async def main() -> tuple[Daemon, object, object]:
        daemon = Daemon(_config(tmp_path), load_model(), model_path=str(model_path))
        try:
            async def control() -> dict[str, Any]:
                answer: dict[str, Any] = msgpack.unpackb(await daemon._answer("load", str(other)))
                return answer

            requests: dict[str, Callable[[], Awaitable[object]]] = {"control": control, "SIGHUP": daemon.reload}
            second = "SIGHUP" if first == "control" else "control"
            held = asyncio.create_task(requests[first]())
            assert await asyncio.to_thread(entered.wait, 30), "the slow load never started"
            later = await asyncio.wait_for(requests[second](), 30)  # requested while the first is being checked, and done
            assert daemon.fingerprint == fast and daemon.stream.next_model is not None and daemon.stream.next_model.fingerprint == fast
            release.set()
            earlier = await asyncio.wait_for(held, 30)
        finally:
            release.set()
            daemon.publisher.close()
        return daemon, earlier, later

    daemon, earlier, later = asyncio.run(main())
    assert daemon.fingerprint == fast and daemon.model is not None and daemon.model.fingerprint == fast  # the last request's
    assert daemon.stream.next_model is not None and daemon.stream.next_model.fingerprint == fast
    said = [r.getMessage() for r in caplog.records if "not swapped in" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0] and str(tmp_path / "slow.npz") in said[0] and slow in said[0], said
    if first == "control":
        assert later is True
        assert isinstance(earlier, dict) and earlier["ok"] is False, earlier
        assert earlier["error"] == (f"{tmp_path / 'slow.npz'}: not swapped in: a later request (SIGHUP load of {model_path}) came "
                                    "while it was checked (the last request wins)"), earlier
    else:
        assert earlier is False and later == {"ok": True, "model": fast}, (earlier, later)
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


def _signal(parts: list[tuple[float, float]], seed: int = 3) -> np.ndarray:
    """(seconds, noise sd in counts) parts, one after the other: rests (sd 20) and slides (sd 2000), int16 (n, 2)."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.standard_normal((round(d * FS), 2)) * sd for d, sd in parts])
    return np.clip(np.rint(x), -32768, 32767).astype(np.int16)


def _run(config: Config, model: Model, data: bytes, between: Callable[[Daemon], None], chunk: int = 4096, **kwargs: Any) -> list[Any]:
    """``data`` (the board's bytes) through a daemon in this process; ``between(daemon)`` after each chunk it took in. Every
    message it published, in order."""
    sent: list[Any] = []
    daemon: Daemon = memory_daemon(config, model, data, chunk, between, **kwargs)
    publish = daemon.publisher.publish

    def keep(msg: Any) -> Any:
        sent.append(msg)
        return publish(msg)

    daemon.publisher.publish = keep  # type: ignore[method-assign]
    asyncio.run(daemon.run())
    return sent


@pytest.mark.parametrize("during", [True, False])
def test_a_shadow_started_mid_stream_labels_the_live_slides_under_their_ids(tmp_path: Path, during: bool) -> None:
    """The audit's shadow, started mid-run, published slide_id 0, 1, 2, ... for the slides the live topics call 34, 35,
    36, ... (and two finals of its slide 15 for the live slide 49 the resumed event names). Started here during the third
    slide (it begins with the fourth), or between the second and the third: its results carry the live slides' ids, starts
    and stops; the slide with a dip (an end, withdrawn by ``resumed``, and the real end) has the shadow's two finals under
    the live id as well. The shadow is the live model under another fingerprint: on the same samples, the same labels."""
    rest, slide = (0.6, 20.0), (0.8, 2000.0)
    parts = [rest, slide, rest, slide, rest, (1.2, 2000.0), rest, slide, rest, (0.6, 2000.0), (0.15, 20.0), (0.6, 2000.0), rest,
             slide, rest]
    data = encode_frames(1000, _signal(parts))
    candidate, fingerprint = _model(tmp_path / "candidate.npz", "a candidate")
    first: list[int] = []  # the first slide the shadow labels: the one after the live slide in progress, or the last one

    def start_shadow(daemon: Daemon) -> None:
        live = daemon.pipeline
        if not first and live.sliding == during and live._slide_id == (2 if during else 1):
            first.append(live._slide_id + 1)
            daemon.set_shadow(candidate)

    sent = _run(_config(tmp_path), load_model(), data, start_shadow)
    assert first == [3 if during else 2], first
    live = [(m.slide_id, m.start, m.stop, m.label, m.confidence) for m in sent if isinstance(m, Roughness) and m.final]
    shadow = [(m.slide_id, m.start, m.stop, m.label, m.confidence) for m in sent if isinstance(m, Shadow) and m.final]
    assert [k[0] for k in live] == [0, 1, 2, 3, 4, 4, 5], live  # slide 4: an end and label withdrawn, then the real one
    assert shadow == [k for k in live if k[0] >= first[0]], (shadow, live)
    resumed = [m.slide_id for m in sent if isinstance(m, Slide) and m.event == schema.SLIDE_RESUMED]
    assert resumed == [4], resumed
    starts = {(m.slide_id, m.start) for m in sent if isinstance(m, Slide) and m.event == schema.SLIDE_START}
    provisional = [m for m in sent if isinstance(m, Shadow) and not m.final]
    assert all((m.slide_id, m.start) in starts for m in provisional), provisional
    assert all(m.model == fingerprint for m in sent if isinstance(m, Shadow))


def test_a_sighup_to_a_model_whose_windows_the_ring_cannot_hold_is_refused_in_one_line(tmp_path: Path,
                                                                                       caplog: pytest.LogCaptureFixture) -> None:
    """A model of 12 s windows (hop 12 s) starts a daemon (its ring is sized for it), but the same file by SIGHUP gave
    ``Task exception was never retrieved`` and a WindowError traceback (control refused it, as an unforeseen error). Both
    now refuse it in one line naming the file, the running model stays, and the daemon goes on."""
    _, long = _model(tmp_path / "longwin.npz", "long windows", duration_s=12.0, hop_s=12.0)
    path = str(tmp_path / "longwin.npz")
    data = encode_frames(1000, _signal([(0.5, 20.0)]))
    caplog.set_level(logging.INFO)
    answers: list[dict[str, Any]] = []
    shipped = load_model()

    def refusals() -> list[str]:
        return [r.getMessage() for r in caplog.records if "reload refused" in r.getMessage()]

    def chunks() -> Iterator[bytes]:
        yield data[: len(data) // 2]
        os.kill(os.getpid(), signal.SIGHUP)  # the daemon's handler: systemctl reload
        deadline = time.monotonic() + 30
        while not refusals():
            assert time.monotonic() < deadline, "no line refusing the reload"
            yield b""  # the loop turns: the reload runs
        yield data[len(data) // 2:]

    async def main() -> Daemon:
        daemon = Daemon(_config(tmp_path), shipped, model_path=path,
                        source_factory=lambda on_bytes, on_state: MemorySource(chunks(), on_bytes, on_state))
        await daemon.run()
        answers.append(msgpack.unpackb(await daemon._answer("load", path)))  # control: the same refusal
        return daemon

    daemon = asyncio.run(main())
    expected = (f"{path}: the model's 12 s windows do not fit the ring (20 s): raise ring.seconds, or restart the daemon with it "
                "(a start sizes the ring for its model; a running one's does not grow)")
    assert refusals() == [f"reload refused, model {shipped.fingerprint} stays: {expected}"] * 2, refusals()
    assert answers == [{"ok": False, "error": expected}], answers
    assert daemon.fingerprint == shipped.fingerprint != long and daemon.stream.next_model is shipped
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR and "reload refused" not in r.getMessage()], caplog.text
    assert daemon.last_status is not None and daemon.last_status.samples > 0.9 * 0.5 * FS


def test_a_swap_is_recorded_by_the_stream_and_applied_by_what_feeds_it_next() -> None:
    """The daemon asks for a swap on its event loop while a worker thread may be feeding the stream a batch: the stream
    only records it (a model whose windows the ring cannot hold is refused at once) and the next feed applies it, on the
    feeding thread, so the pipeline never changes model under a batch being analysed."""
    from tactiled.errors import WindowError
    from tactiled.run.stream import Stream

    old, new = load_model(), load_model()
    stream = Stream(Config(), old, fs=old.fs, channels=old.channels)
    stream.swap_model(new)
    assert stream.live.model is old and stream.next_model is new  # recorded, not applied
    stream.feed_samples(0, np.zeros((400, old.channels), dtype=np.int16))
    assert stream.live.model is new  # applied by the next feed (no slide in progress)
    huge = load_model()
    huge.settings = replace(huge.settings, duration_s=60.0)
    with pytest.raises(WindowError, match="do not fit the ring"):
        stream.swap_model(huge)
    stream.feed_samples(400, np.zeros((400, old.channels), dtype=np.int16))
    assert stream.live.model is new
