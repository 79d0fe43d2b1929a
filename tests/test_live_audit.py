"""Defects an audit found in the live side (config, control socket, daemon, monitor, demo), each pinned by a check."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rich.console import Console
from tactiled_client import BlockingSubscriber, NoData, Roughness, Slide, Status, schema

from tactiled.apps.monitor import MonitorState, render
from tactiled.config import in_use, parse_config
from tactiled.errors import ConfigError, TactiledError
from tests.conftest import REPO, board_and_daemon, run_cli, tactiled_cmd, wait_for
from tests.test_daemon import raw_request


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``tactiled ARGV`` in this process: its exit code and what it wrote on stderr."""
    from tactiled.cli.main import main

    code = main(argv)
    return code, capsys.readouterr().err


@pytest.mark.parametrize(("text", "message"), [
    ('[model]\npath = "a\\u0000b"\n', "model.path: holds a NUL character"),
    ('[model]\nshadow = "a\\u0000b"\n', "model.shadow: holds a NUL character"),
    ('[publish]\nendpoint = "ipc:///tmp/a\\u0000b"\n', "publish.endpoint: holds a NUL character"),
    ('[publish]\nendpoint = "tcp://127.0.0.1:99999"\n', "publish.endpoint: .*port '99999' is not a number in 0..65535"),
    ('[publish]\nendpoint = "tcp://127.0.0.1"\n', "publish.endpoint: .*needs a host and a port"),
    ('[publish]\nendpoint = "inproc://x"\n', "publish.endpoint: .*reachable from this process only"),
    ('[control]\nendpoint = "tcp://127.0.0.1:99999"\n', "control.endpoint: .*port '99999'"),
    ('[control]\nendpoint = "tcp://127.0.0.1"\n', "control.endpoint: .*needs a host and a port"),
    ('[control]\nendpoint = "tcp://127.0.0.1:*"\n', "control.endpoint: .*port '\\*'"),
    ('[control]\nendpoint = "inproc://x"\n', "control.endpoint: must be empty"),
    ('[publish]\nendpoint = "ipc:///tmp/p.sock"\n[control]\nendpoint = "ipc:///tmp/./p.sock"\n', "control.endpoint: is publish.endpoint's socket"),
    ('[publish]\nendpoint = "tcp://127.0.0.1:7350"\n[control]\nendpoint = "tcp://127.0.0.1:7350"\n', "control.endpoint: is publish.endpoint's"),
])
def test_config_refuses_nul_characters_and_endpoints_run_cannot_serve(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        parse_config(text, "x.toml")
    assert str(err.value).startswith("x.toml: ") and "\n" not in str(err.value) and "\0" not in str(err.value)


def test_control_on_the_default_publish_socket_is_refused() -> None:
    """publish.endpoint auto is ipc://<runtime folder>/<sensor id>.sock: a control socket there would take it over."""
    folder = os.environ["TACTILED_RUNTIME_DIR"]
    with pytest.raises(ConfigError, match=r"control\.endpoint: is publish\.endpoint's socket"):
        parse_config(f'[sensor]\nid = "s9"\n[control]\nendpoint = "ipc://{folder}/s9.sock"\n')
    assert parse_config(f'[sensor]\nid = "s9"\n[control]\nendpoint = "ipc://{folder}/s9.control"\n').control.endpoint


def test_check_config_on_endpoints_and_a_fifo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A FIFO as the config hung check-config, run and monitor; a NUL in model.path was a traceback (exit 1); an ipc folder
    that does not exist was ok: an error, but only a note under /run (systemd makes /run/tactiled when the unit starts)."""
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    res = run_cli("check-config", str(fifo), timeout=30)  # a process: without the check it would hang this one
    assert res.returncode == 2 and res.stderr.strip() == f"tactiled: error: {fifo}: cannot read config: not a regular file " \
                                                         "(a device, FIFO or folder is never read)", res.stderr
    for argv in (["run", "--config", str(fifo)], ["monitor", "--config", str(fifo)]):
        code, err = cli(argv, capsys)
        assert code == 2 and err.count("\n") == 1 and "not a regular file" in err, err
    config = tmp_path / "c.toml"
    config.write_text('[model]\npath = "a\\u0000b"\n')
    code, err = cli(["check-config", str(config)], capsys)
    assert code == 2 and err.count("\n") == 1 and "model.path: holds a NUL character" in err and "\0" not in err, err
    config.write_text('[control]\nendpoint = "ipc:///nonexistent-tactiled/x.sock"\n')
    code, err = cli(["check-config", str(config)], capsys)
    assert code == 2 and err.count("\n") == 1 and "control.endpoint: the folder /nonexistent-tactiled does not exist" in err, err
    config.write_text('[publish]\nendpoint = "ipc:///run/tactiled-audit-none/x.sock"\n')
    code, err = cli(["check-config", str(config)], capsys)
    assert code == 0 and "note: publish.endpoint: the folder /run/tactiled-audit-none does not exist" in err, err


@pytest.mark.parametrize("connect", ["foo", "tcp://127.0.0.1"])
def test_monitor_refuses_an_endpoint_it_cannot_connect_to_in_one_line(connect: str, capsys: pytest.CaptureFixture[str]) -> None:
    """It was a zmq.error.ZMQError traceback."""
    code, err = cli(["monitor", "--connect", connect], capsys)
    assert code == 2 and err.startswith(f"tactiled: error: --connect {connect}: must be tcp://HOST:PORT or ipc://PATH") and err.count("\n") == 1


def test_monitor_refuses_a_configs_endpoint_no_subscriber_can_connect_to_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A daemon may bind tcp://*:PORT; a subscriber cannot connect there (a UsageError traceback from the client library)."""
    config = tmp_path / "c.toml"
    config.write_text('[publish]\nendpoint = "tcp://*:7351"\nallow_remote = true\n')
    code, err = cli(["monitor", "--config", str(config)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith("tactiled: error: publish.endpoint tcp://*:7351 (a subscriber connects there): must be tcp://HOST:PORT or ipc://PATH"), err


def test_connect_endpoints_no_daemon_can_be_at_are_refused() -> None:
    """ZeroMQ connects to these without a word (a port taken modulo 65536, an inproc name of the monitor's own process)."""
    import argparse

    from tactiled.cli.cmd_live import subscriber_endpoint
    from tactiled.config import Config

    def check_connect(connect: str) -> None:
        subscriber_endpoint(argparse.Namespace(connect=connect), Config())

    for connect in ("tcp://127.0.0.1:70000", "tcp://127.0.0.1:0", "inproc://x", "tcp://127.0.0.1:*"):
        with pytest.raises(TactiledError, match="--connect"):
            check_connect(connect)
    check_connect("tcp://robot.local:7350")
    check_connect("ipc:///run/tactiled/fingertip0.sock")


def test_monitor_blanks_stale_figures_and_shows_every_loss_counter() -> None:
    """After the daemon dies the state said NO DATA but the last rate and slide stayed; restarts, duplicate frames, dropped
    messages and load shedding were never shown."""
    model = MonitorState()
    model.update(schema.status("s", state=schema.STATE_SLIDING, fs_nominal=20_000.0, fs_measured=20_160.0, restarts=2,
                               duplicate_frames=5, dropped_messages=3, overloaded=4000, level=[0.01, 0.02]))
    model.update(schema.slide_start("s", 4, 1000, 20_000.0))

    def screens() -> tuple[str, str]:
        big = Console(file=io.StringIO(), width=140, record=True, color_system=None)
        big.print(render(model, "ipc://x"))
        small = Console(file=io.StringIO(), width=80, height=24, record=True, color_system=None)
        small.print(render(model, "ipc://x", 80, 24))
        return big.export_text(), small.export_text()

    for text in screens():
        assert "20160" in text and "slide 4 since" in text
        assert "restarts 2" in text and "duplicate frames 5" in text and "dropped msgs 3" in text and "overloaded 4000" in text, text
        assert "input shed" not in text and "bad headers" not in text  # 0: not shown
    assert not model.check_stale(model.last_message + 1.0)
    assert model.check_stale(model.last_message + 10.0)
    for text in screens():
        assert " NO DATA " in text and "20160" not in text and "slide 4" not in text and "10.00" not in text, text
    big, small = screens()
    assert "rate - (no data for 10 s)" in big and "- Hz" in small


def test_control_socket_is_shared_like_the_publish_socket_refused_when_taken_and_status_is_real_and_sighup_loads_model_path(
        tmp_path: Path) -> None:
    """One daemon: its control socket is mode 660 (it was 755: the tactiled group could not connect); a second daemon on the
    same control.endpoint is refused in one line (it took the socket over); a control status has real seq, time and rate
    (it had 0, 0.0, 0.0); after a control load, SIGHUP loads model.path again, not the loaded file."""
    from tactiled.learn.model import load_model

    shipped = load_model()
    a = shipped.fingerprint
    shipped.summary = {**shipped.summary, "note": "the same classifier under another fingerprint"}
    b = shipped.save(tmp_path / "b.npz")
    ctl = f"ipc://{tmp_path}/control"
    config = tmp_path / "c.toml"
    config.write_text(f'[control]\nendpoint = "{ctl}"\n')
    with board_and_daemon(tmp_path, "--config", str(config)) as live, BlockingSubscriber(live.endpoint, topics=["status"], timeout=30) as sub:
        def streaming() -> Status | None:
            m = sub.receive()
            return m if isinstance(m, Status) and m.seq >= 2 and m.fs_measured > 0 and m.state != schema.STATE_DISCONNECTED else None
        wait_for(streaming, timeout=60, what="statuses of a streaming board")
        assert stat.S_IMODE(os.stat(tmp_path / "control").st_mode) == 0o660
        reply = raw_request(ctl, {"cmd": "status"})
        assert isinstance(reply, dict) and reply["ok"], reply
        status = reply["status"]
        assert status["seq"] >= 2 and abs(status["time_unix"] - time.time()) < 10 and status["fs_measured"] > 1000, status
        second = subprocess.run(tactiled_cmd("run", "--config", str(config), "--port", str(tmp_path / "none"), "--publish",
                                             f"ipc://{tmp_path}/pub2", "--no-model"), capture_output=True, text=True, timeout=30, cwd=REPO)
        assert second.returncode == 2 and second.stderr.strip().splitlines() == [
            f"tactiled: error: {config}: control.endpoint: another process already listens on {ctl} (another daemon's control socket?); "
            "stop it or give this one another endpoint"], second.stderr
        assert raw_request(ctl, {"cmd": "load", "path": str(tmp_path / "b.npz")}) == {"ok": True, "model": b}  # still the first's

        def status_of(model: str) -> bool:
            try:
                m = sub.receive(timeout=5)
            except NoData:
                return False
            return isinstance(m, Status) and m.model == model
        wait_for(lambda: status_of(b), timeout=30, what="a status of the loaded model")
        live.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: status_of(a), timeout=60, what="the model of model.path back after SIGHUP")
        err = live.stop()
    assert live.proc.returncode == 0 and "reload refused" not in err, err[-2000:]


def test_demo_cleans_up_on_sighup(tmp_path: Path) -> None:
    """Closing the demo's terminal (SIGHUP) left its daemon running for ever and its temporary folder behind."""
    endpoint = f"ipc://{tmp_path}/demo.sock"
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    demo = subprocess.Popen([sys.executable, "-m", "tactiled", "demo", "--headless", "--seconds", "120", "--publish", endpoint],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        with BlockingSubscriber(endpoint, topics=["status"], timeout=60) as sub:
            wait_for(lambda: isinstance(sub.receive(), Status), timeout=60, what="the demo's daemon publishing")
        assert len(list(tmp_path.glob("tactiled-demo-*"))) == 1
        demo.send_signal(signal.SIGHUP)
        demo.wait(30)
        assert demo.returncode == 128 + signal.SIGHUP
        assert not list(tmp_path.glob("tactiled-demo-*"))  # the folder went with the demo
        assert not in_use(endpoint)  # and its daemon: nobody listens on its socket any more
    finally:
        if demo.poll() is None:
            demo.kill()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(demo.pid, signal.SIGKILL)  # whatever of its session is left (the daemon, orphaned without the fix)
        demo.wait(10)


def test_a_slide_in_progress_when_the_port_goes_ends_then_with_its_label(tmp_path: Path) -> None:
    """An unplug in the middle of a slide left it open until the board came back, then ended it as end_of_stream (a
    replay's reason) with a late label, or none if the board never came back. The virtual board of seed 0 slides from
    19.07 s to 20.56 s of sensor time (its schedule is the seed's); it is unplugged at 20.0 s and stays away."""
    fs = 20_000
    with board_and_daemon(tmp_path, seed=0, unplug_at=[20.0], unplug_s=600.0) as live, \
            BlockingSubscriber(live.endpoint, topics=["slide", "roughness"], timeout=30) as sub:
        got: list[object] = []

        def ended() -> bool:
            got.append(sub.receive())
            return isinstance(got[-1], Slide) and got[-1].event == schema.SLIDE_END and got[-1].stop > 19.5 * fs
        wait_for(ended, timeout=60, what="the end of the slide the unplug cut")
        end = got[-1]
        assert isinstance(end, Slide) and end.reason == "disconnected", end
        assert abs(end.start - 19.07 * fs) < 0.2 * fs and 19.5 * fs < end.stop <= 20.0 * fs, end

        def final() -> Roughness | None:
            m = sub.receive()
            return m if isinstance(m, Roughness) and m.final and m.slide_id == end.slide_id else None
        label = wait_for(final, timeout=30, what="the final label of the cut slide")
        assert isinstance(label, Roughness) and label.quality["windows"] >= 1 and label.stop == end.stop, label
    assert not any(isinstance(m, Slide) and m.reason == "end_of_stream" for m in got)


def test_an_error_answering_a_control_request_is_one_error_reply_and_the_daemon_runs_on(tmp_path: Path,
                                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A request the checks miss (a load whose path os.stat could not take stopped the daemon in an audit) raises inside
    the answer: the requester gets one error reply naming the exception, and the next request is answered."""
    import asyncio
    from collections.abc import Iterator

    import msgpack
    import zmq

    from tactiled.board.serialsource import MemorySource
    from tactiled.config import Config
    from tactiled.learn.model import load_model
    from tactiled.service.daemon import Daemon

    answer = Daemon._answer

    async def failing(self: Daemon, cmd: str, path: str | None) -> bytes:
        if cmd == "load":
            raise RuntimeError("what no check foresaw")
        return await answer(self, cmd, path)

    monkeypatch.setattr(Daemon, "_answer", failing)
    ctl = f"ipc://{tmp_path}/control"
    config = Config().override({"publish.endpoint": f"ipc://{tmp_path}/pub", "control.endpoint": ctl})
    req = zmq.Context.instance().socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    replies: list[dict[str, object]] = []

    def chunks() -> Iterator[bytes]:
        """Each request sent and its reply awaited while the daemon's loop runs (the source yields to it), then the end."""
        for request in ({"cmd": "load", "path": "m.npz"}, {"cmd": "status"}):
            req.send(msgpack.packb(request))
            deadline = time.monotonic() + 30
            while not req.poll(0):
                assert time.monotonic() < deadline, f"no reply to {request}"
                yield b""
            replies.append(msgpack.unpackb(req.recv()))

    async def main() -> None:
        daemon = Daemon(config, load_model(), source_factory=lambda on_bytes, on_state: MemorySource(chunks(), on_bytes, on_state))
        req.connect(ctl)
        await daemon.run()  # returns at the end of the stream

    try:
        asyncio.run(main())
    finally:
        req.close()
    assert replies[0] == {"ok": False, "error": "RuntimeError: what no check foresaw"}, replies
    assert replies[1]["ok"] is True and isinstance(replies[1]["status"], dict), replies
