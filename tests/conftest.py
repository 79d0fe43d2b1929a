"""Shared test helpers: waiting on events with a timeout, the CLI as a process and its usage errors, a virtual board
and a daemon on it, simulated recordings, what a bridge hands its outlets."""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

if TYPE_CHECKING:
    from tactiled.files.recording import Recording
    from tactiled.sim.physics import SimParams
    from tactiled.sim.virtualboard import VirtualBoard

REPO = Path(__file__).resolve().parents[1]
# daemons started without --publish bind ipc://$TACTILED_RUNTIME_DIR/<sensor id>.sock: one folder per test process,
# so that parallel test processes never meet (tactiled_client.endpoints)
os.environ["TACTILED_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="tactiled-run-")
atexit.register(shutil.rmtree, os.environ["TACTILED_RUNTIME_DIR"], ignore_errors=True)  # gone with the test process
# child processes (the CLI, the client's python -m tactiled_client) import the checkout's client library too, as this
# process does (pytest's pythonpath, pyproject.toml), rather than the copy pip installed from ./clients
os.environ["PYTHONPATH"] = os.pathsep.join([str(REPO / "clients"), *filter(None, [os.environ.get("PYTHONPATH")])])


def wait_for(predicate: Callable[[], object], timeout: float = 20.0, what: str = "condition") -> object:
    """Call ``predicate`` until it returns something truthy; fail after ``timeout`` seconds.

    ``predicate`` must itself wait for the next event (e.g. a subscriber's ``receive`` with a
    timeout), so this loop never sleeps or spins.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def standing_finals(messages: list[Any]) -> list[Any]:
    """The final roughness messages of ``messages`` that stood: a ``resumed`` slide message withdraws the final label
    of its slide published before it (docs/messages.md, *Early ends and withdrawals*)."""
    out: list[Any] = []
    for m in messages:
        if getattr(m, "type", "") == "roughness" and m.final:
            out.append(m)
        elif getattr(m, "type", "") == "slide" and m.event == "resumed":
            out = [r for r in out if not (r.slide_id == m.slide_id and r.sensor == m.sensor)]
    return out


def tactiled_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "tactiled", *args]


def run_cli(*args: str, timeout: float = 120.0, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(tactiled_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=REPO, **kw)  # type: ignore[call-overload, no-any-return]


def cli_here(capture: pytest.CaptureFixture[str] | None, *args: str) -> subprocess.CompletedProcess[str]:
    """``tactiled ARGS`` run by :func:`tactiled.cli.main.main` in this process, as :func:`run_cli` reports it (exit code,
    stdout, stderr): the same handler and lines without a new interpreter's start-up, and with this process's worker pool
    (joblib's loky executor, started once per test process) instead of a new one per command. For a test about the
    command's output, files and exit code, not about a process (signals, a daemon, start-up, the environment).

    ``capture``: the test's ``capfd`` (output read at the file descriptors) or ``capsys``; None (in a fixture wider than a
    test) redirects ``sys.stdout`` and ``sys.stderr`` instead. What a process would also have written to stderr is written
    there: warnings as Python's default filters show them (pytest would otherwise keep them to its summary) and log
    records as :func:`main`'s logging set-up prints them (pytest's handlers on the root logger make that set-up a no-op
    here). An argparse exit is its code; cwd is this process's, so give paths in full."""
    import io
    import logging
    import warnings

    from tactiled.cli.main import main

    if capture is not None:
        capture.readouterr()  # what the test wrote before is not the command's
    out, err = io.StringIO(), io.StringIO()
    with contextlib.ExitStack() as stack:
        if capture is None:
            stack.enter_context(contextlib.redirect_stdout(out))
            stack.enter_context(contextlib.redirect_stderr(err))
        stack.enter_context(warnings.catch_warnings())
        warnings.resetwarnings()  # Python's defaults (the warnings module's docs): shown once per place, but deprecations
        warnings.simplefilter("default")
        for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
            warnings.simplefilter("ignore", category)
        warnings.showwarning = lambda message, category, filename, lineno, file=None, line=None: sys.stderr.write(
            warnings.formatwarning(message, category, filename, lineno, line))
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("tactiled: %(levelname)s: %(message)s"))
        handler.setLevel(logging.WARNING)  # main's level without -v (not for a command run with -v)
        root = logging.getLogger()
        root.addHandler(handler)
        stack.callback(root.removeHandler, handler)
        try:
            code = main(list(args))
        except SystemExit as exc:  # argparse: usage errors (2), --help and --version (0)
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        sys.stdout.flush()
        sys.stderr.flush()
    if capture is not None:
        stdout, stderr = capture.readouterr()
    else:
        stdout, stderr = out.getvalue(), err.getvalue()
    return subprocess.CompletedProcess(["tactiled", *args], code, stdout, stderr)


def surfaces_but_one(root: Path, surfaces: int, seed: int) -> tuple[Path, list[Path], list[str]]:
    """A robot-scene dataset of ``surfaces`` surfaces (2 files x 3 slides each) simulated into ``root``/d: the folder, the files
    of every surface but the last (to train on), and the surface names in order (the last one left out)."""
    data = root / "d"
    from tactiled.sim.simulate import write_dataset  # the command's files, in this process (no second of SciPy imports)

    write_dataset(data, scene="robot", surfaces=str(surfaces), files_per_surface=2, slides_per_file=3, seed=seed)
    names = sorted({p.name.split("_")[1] for p in data.glob("*.npz")})
    return data, [p for p in sorted(data.glob("*.npz")) if f"_{names[-1]}_" not in p.name], names


@pytest.fixture
def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONUNBUFFERED"] = "1"
    return e


def lossy_recording(first_index: int, meta: dict[str, object] | None = None, *, slides: int = 3, seed: int = 7,
                    lost: tuple[tuple[int, int], ...] = ((1000, 37), (50_000, 20))) -> Recording:
    """A simulated recording of Ra2.29 (``slides`` slides, ``seed``) with its ground truth, ``first_index`` and the
    ``lost`` ranges (position, count) zeroed and listed."""
    from tactiled.files.recording import Recording
    from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file

    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra2.29")[0], slides, seed)
    ranges = np.array(lost, dtype=np.int64).reshape(-1, 2)
    samples = sim.samples.copy()
    for p, c in ranges:
        samples[p:p + c] = 0
    return Recording(samples, params.fs, params.volts_per_count, slide_start=np.array([t.start for t in sim.truth]),
                     slide_stop=np.array([t.stop for t in sim.truth]), surface=np.array([t.surface.name for t in sim.truth]),
                     first_index=first_index, lost=ranges, meta=meta or {})


def live_events(rec: Recording, config: Any, model: Any, block: int = 800) -> list[Any]:
    """The daemon's path, the reference for replay: a Stream fed ``rec`` in blocks of ``block`` samples (800: 40 ms at
    20 kHz) as they come, then ended; every pipeline event (sensor indices)."""
    from tactiled.run.stream import Stream

    stream = Stream.for_recording(rec, config, model)
    valid = rec.valid_mask()
    events: list[Any] = []
    for lo in range(0, rec.samples.shape[0], block):
        events += stream.feed_samples(rec.first_index + lo, rec.samples[lo: lo + block], valid[lo: lo + block]).events
    return events + stream.finish().events


def memory_daemon(config: Any, model: Any, data: bytes, chunk: int, probe: Callable[[Any], None], **kwargs: Any) -> Any:
    """A :class:`~tactiled.service.daemon.Daemon` (not yet run) on a memory source of the board's bytes ``data`` in chunks
    of ``chunk`` bytes, ``probe(daemon)`` called after each chunk it consumed; ``kwargs`` to the daemon."""
    from tactiled.board.serialsource import MemorySource
    from tactiled.service.daemon import Daemon

    box: list[Daemon] = []

    def factory(on_bytes: Callable[[bytes], Any], on_state: Callable[[str, str], None]) -> MemorySource:
        async def consume(b: bytes) -> None:
            await on_bytes(b)
            probe(box[0])

        return MemorySource((data[i:i + chunk] for i in range(0, len(data), chunk)), consume, on_state)

    box.append(Daemon(config, model, source_factory=factory, **kwargs))
    return box[0]


def recorder_thread(endpoint: str, out: Path, stop: threading.Event, on_message: Callable[[int], None],
                    refused: list[Any]) -> threading.Thread:
    """The client library's session recorder (``tactiled_client.record.record``) of ``endpoint`` into ``out``, started in a
    thread: until ``stop`` is set, ``on_message(n)`` after each message written, every refusal appended to ``refused``."""
    from tactiled_client.record import record

    thread = threading.Thread(target=record, args=(endpoint, out),
                              kwargs={"stop": stop.is_set, "on_message": on_message, "on_refused": refused.append}, daemon=True)
    thread.start()
    return thread


class BridgeSink:
    """What a bridge hands to its outlets, kept: every samples, roughness and status message in order (``got``);
    ``stopping`` is set at the daemon's last status, ``closed`` when the bridge closes its outlets."""

    def __init__(self) -> None:
        self.got: list[object] = []
        self.stopping = threading.Event()
        self.closed = threading.Event()

    def samples(self, msg: object) -> None:
        self.got.append(msg)

    def roughness(self, msg: object) -> None:
        self.got.append(msg)

    def withdrawn(self, msg: object) -> None:
        self.got.append(msg)

    def status(self, msg: object) -> None:
        self.got.append(msg)
        if getattr(msg, "state", None) == "stopping":  # schema.STATE_STOPPING
            self.stopping.set()

    def close(self) -> None:
        self.closed.set()


def usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The CLI's answer to a bad command line, run in this process: asserts exit 2 and exactly one line on stderr, returns it."""
    from tactiled.cli.main import main

    with pytest.raises(SystemExit) as done:
        main(argv)
    err = capsys.readouterr().err
    assert done.value.code == 2 and len(err.strip().splitlines()) == 1, err
    return err.strip()


@contextlib.contextmanager
def in_thread(run: Callable[[threading.Event], Any]) -> Iterator[None]:
    """``run(stop)`` in a thread of its own for the block; ``stop`` set and the thread joined when the block ends."""
    stop = threading.Event()
    thread = threading.Thread(target=run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(10)


@contextlib.contextmanager
def running(board: VirtualBoard) -> Iterator[VirtualBoard]:
    """``board`` (opened if it was not) streaming from a thread of its own; stopped and joined when the block ends."""
    if not board.path:
        board.open()
    with in_thread(board.run):
        yield board


@contextlib.contextmanager
def daemon_process(port: str, endpoint: str, *args: str, preexec_fn: Callable[[], None] | None = None) -> Iterator[subprocess.Popen[str]]:
    """``tactiled run --port PORT --publish ENDPOINT ARGS`` as a process (stderr piped; ``preexec_fn`` run in the child before
    it starts, e.g. a resource limit); terminated when the block ends (killed if it does not stop within 30 s). Its
    ``returncode`` and ``stderr`` are there to check afterwards."""
    proc = subprocess.Popen(tactiled_cmd("run", "--port", port, "--publish", endpoint, *args), stderr=subprocess.PIPE, text=True,
                            preexec_fn=preexec_fn)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


@dataclass
class Live:
    """A virtual board on a pty and ``tactiled run`` reading it (:func:`board_and_daemon`)."""

    link: str  # the pty's stable path
    endpoint: str  # where the daemon publishes
    board: VirtualBoard
    proc: subprocess.Popen[str]
    log_path: Path  # the board's event log (sim.virtualboard.read_log)

    def stop(self, timeout: float = 30.0) -> str:
        """Terminate the daemon (as systemd stops it) and wait; returns what it wrote on stderr."""
        self.proc.terminate()
        _, err = self.proc.communicate(timeout=timeout)
        return err or ""

    def overrun_samples(self, from_index: int) -> int:
        """Samples at board index ``from_index`` or later that the board could not write because the pty was full (the
        daemon, starved of CPU on a loaded machine, read too late): a loss the board logs, not one the daemon made.
        Read it after the block has stopped the board (its log is flushed then)."""
        from tactiled.sim.virtualboard import read_log

        return sum(e["count"] for e in read_log(self.log_path) if e["event"] == "overrun" and e["index"] >= from_index)


@contextlib.contextmanager
def board_and_daemon(tmp_path: Path, *run_args: str, params: SimParams | None = None, surfaces: int = 3, seed: int = 0,
                     speed: float = 3.0, **board_options: Any) -> Iterator[Live]:
    """A virtual board (``params``, ``surfaces`` surfaces, ``seed``; faults as :class:`VirtualBoard` options) streaming on
    ``tmp_path/tty`` at ``speed`` × real time, logging to ``tmp_path/board.jsonl``, and ``tactiled run`` on it publishing
    on ``ipc://tmp_path/pub`` with ``run_args``; both stopped when the block ends."""
    from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
    from tactiled.sim.virtualboard import VirtualBoard

    link, endpoint, log_path = str(tmp_path / "tty"), f"ipc://{tmp_path}/pub", tmp_path / "board.jsonl"
    with open(log_path, "w") as log:
        board = VirtualBoard(SensorSimulator(params or SimParams(), seed=seed), pick_surfaces(surfaces), link=link, speed=speed, seed=seed,
                             log=log, **board_options)
        with running(board), daemon_process(link, endpoint, *run_args) as proc:
            yield Live(link, endpoint, board, proc, log_path)


@contextlib.contextmanager
def xpub_socket(endpoint: str) -> Iterator[Any]:
    """A ZeroMQ XPUB bound at ``endpoint`` (no linger), closed when the block ends: a publisher a test drives by hand,
    which sees each subscription as a message."""
    import zmq

    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(endpoint)
    try:
        yield sock
    finally:
        sock.close(linger=0)


@contextlib.contextmanager
def status_publisher(endpoint: str, every_s: float = 0.02, payload: int = 0) -> Iterator[threading.Event]:
    """An XPUB on ``endpoint`` that, once a subscriber has subscribed (the event it yields is set then), sends a status
    message (with a ``note`` of ``payload`` bytes) every ``every_s`` without a pause, until the block ends: the busy topic
    that never leaves a quiet moment."""
    import msgpack
    import zmq
    from tactiled_client import schema

    subscribed, stop = threading.Event(), threading.Event()

    def run(sock: zmq.Socket[bytes]) -> None:
        seq = 0
        while not stop.is_set():
            if not subscribed.is_set():
                if sock.poll(50):
                    sock.recv()
                    subscribed.set()
                continue
            body = {"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": "s0", "type": "status", "state": "idle",
                    **({"note": "x" * payload} if payload else {})}
            sock.send_multipart([b"status/s0", msgpack.packb(body, use_bin_type=True)])
            seq += 1
            stop.wait(every_s)  # the publisher's pace, not a synchronisation

    with xpub_socket(endpoint) as sock:
        thread = threading.Thread(target=run, args=(sock,), daemon=True)
        thread.start()
        try:
            yield subscribed
        finally:
            stop.set()
            thread.join(10)
