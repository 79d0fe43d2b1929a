"""``tactiled demo``: a virtual board on a pty, the daemon on it with the shipped model, and the monitor (or, headless,
one line per label with the surface the simulator really slid over).

Both helpers run as processes of their own (``tactiled simulate serial`` and ``tactiled run``), as a user would start
them; their files live in a temporary folder that goes when the demo ends (Ctrl-C, SIGTERM, or SIGHUP when its terminal
closes, stop both first). If no label comes within a headless run, the
demo says so with the daemon's last log line (exit 1).
"""

from __future__ import annotations

import contextlib
import errno
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from tactiled_client import BlockingSubscriber, NoData, Roughness, Slide, schema
from tactiled_client.truth import overlapping

from tactiled.apps.monitor import read_truth, run_monitor
from tactiled.config import in_use
from tactiled.errors import ConfigError
from tactiled.signals import sigterm_as_exit

DEMO_REST_FIRST_S = 1.5  # the virtual board's rest before its first slide, s: the daemon is reading by then
DAEMON_LAST_WORDS_S = 10.0  # how long a daemon that gave no label may take to exit and say why, s


def run_demo(scene: str = "hand", seed: int = 0, publish: str | None = None, headless: bool = False, seconds: float = 20.0) -> int:
    """Run the demo (see the module docstring) on ``scene`` with ``seed``, publishing on ``publish`` (default: an ipc socket in
    the temporary folder); ``headless``: label lines for ``seconds`` of wall time instead of the monitor. Exit code: 0 if
    final labels came (headless) or the monitor was quit, 1 if not."""
    # SIGHUP too (its terminal closed): the daemon child would take it for a reload and outlive the demo
    with sigterm_as_exit((signal.SIGTERM, signal.SIGHUP)), tempfile.TemporaryDirectory(prefix="tactiled-demo-") as tmp:
        link, board_log, daemon_log = f"{tmp}/tty", f"{tmp}/board.jsonl", Path(tmp) / "daemon.log"
        endpoint = publish or f"ipc://{tmp}/pub"
        if in_use(endpoint) or tcp_port_taken(endpoint):  # the daemon would refuse it; the labels shown would be the other process's
            raise ConfigError(f"demo --publish: another process already publishes on {endpoint} (another demo or daemon?); "
                              "stop it or give this demo another endpoint")
        exe = [sys.executable, "-m", "tactiled"]
        started: list[subprocess.Popen[str] | subprocess.Popen[bytes]] = []  # stopped however the demo ends, even while starting them
        try:
            # the board starts at rest long enough for the daemon to be reading by the first slide: a daemon started in a
            # slide cannot end it before a longer quiet than the scene's rests, and its first label would come late
            board = subprocess.Popen([*exe, "simulate", "serial", "--link", link, "--scene", scene, "--seed", str(seed), "--log", board_log,
                                      "--rest-first", str(DEMO_REST_FIRST_S)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            started.append(board)
            assert board.stdout is not None
            board.stdout.readline()  # the device path: the pty exists from here on
            with open(daemon_log, "w") as log:
                daemon = subprocess.Popen([*exe, "run", "--port", link, "--publish", endpoint, "--samples"], stderr=log)
            started.append(daemon)
            def running() -> bool:  # a daemon that fails (a tcp port it cannot bind) exits: what came is not its labels
                return daemon.poll() is None

            if not headless:  # the simulator's log: the true surface of every slide
                if run_monitor(endpoint, board_log, running) == 0:  # q or Ctrl-C (which the daemon child gets too)
                    return 0
                failed = "the daemon stopped"
            else:
                labels = print_labels(endpoint, seconds, board_log, running)
                if labels and running():
                    return 0
                failed = "the daemon stopped" if not running() else f"no final label in {seconds:g} s"
                if running():  # on a loaded machine it may still be starting
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        daemon.wait(DAEMON_LAST_WORDS_S)
            last = [line for line in daemon_log.read_text(errors="replace").splitlines() if line.strip()]
            print(f"tactiled: {failed}; the daemon's last words: {last[-1] if last else '(nothing)'}", file=sys.stderr)
            return 1
        finally:
            stop_processes(*reversed(started))


def tcp_port_taken(endpoint: str) -> bool:
    """Whether ``endpoint`` is ``tcp://HOST:PORT`` with a port another socket already listens on (a bind there fails)."""
    if not endpoint.startswith("tcp://"):
        return False
    host, _, port = endpoint[6:].rpartition(":")
    if not port.isdigit() or host in ("", "*"):
        return False
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as ZeroMQ binds: a port in TIME_WAIT is free
        try:
            probe.bind((host, int(port)))
        except OSError as exc:  # another error (a host not of this machine) is the daemon's to say
            return exc.errno == errno.EADDRINUSE
    return False


def print_labels(endpoint: str, seconds: float, board_log: str, running: Callable[[], bool] = lambda: True) -> int:
    """Print one line per roughness message from ``endpoint`` for ``seconds`` (wall time), or until ``running()`` is False
    (the daemon stopped), with the true surface from the virtual board's log ``board_log``; returns how many final labels came."""
    def truth(start: int, stop: int) -> str:
        return overlapping(read_truth(board_log), start, stop) or "?"

    labels = 0
    deadline = time.monotonic() + seconds
    with BlockingSubscriber(endpoint, topics=["roughness", "slide"], timeout=1.0) as sub:
        while time.monotonic() < deadline and running():
            try:
                msg = sub.receive(timeout=min(1.0, max(0.01, deadline - time.monotonic())))
            except NoData:
                continue
            if isinstance(msg, Slide) and msg.event == schema.SLIDE_RESUMED:
                print(f"slide {msg.slide_id}: label withdrawn, the slide goes on", flush=True)
                continue
            if not isinstance(msg, Roughness):
                continue
            kind = "final" if msg.final else f"provisional after {msg.used_s:.2f} s"
            why = f" [{msg.reason}]" if msg.reason else ""
            print(f"slide {msg.slide_id}: {msg.label or '-'} ({msg.confidence or 0:.2f}, {kind}){why}, true surface {truth(msg.start, msg.stop)}",
                  flush=True)
            labels += bool(msg.final and msg.label)
    return labels


def stop_processes(*procs: subprocess.Popen[bytes] | subprocess.Popen[str], grace_s: float = 5.0) -> None:
    """Send SIGTERM to every process in ``procs``, wait ``grace_s`` seconds for each, then SIGKILL what is left."""
    for proc in procs:
        proc.terminate()
    for proc in procs:
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
