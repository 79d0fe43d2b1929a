"""The monitor and the bridges against a daemon that requires ZeroMQ CURVE (an outside audit, nineteenth session: they had
no way to pass a key, waited for ever, and their messages pointed elsewhere).

A real daemon process with CURVE on an ipc socket, the bridge loop subscribing to it.
"""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path

import pytest
from tactiled_client import Status

from tactiled.apps.bridges import run_bridge
from tests.conftest import cli_here, run_cli, tactiled_cmd, wait_for


class _Statuses:
    """A bridge sink that keeps the statuses it is given."""

    def __init__(self) -> None:
        self.statuses: list[Status] = []
        self.got = threading.Event()

    def samples(self, msg: object) -> None: ...
    def roughness(self, msg: object) -> None: ...
    def withdrawn(self, msg: object) -> None: ...
    def close(self) -> None: ...

    def status(self, msg: Status) -> None:
        self.statuses.append(msg)
        self.got.set()


def test_the_monitor_and_bridges_take_curve_keys_and_say_when_they_need_them(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Without ``--curve``, ``monitor`` and ``lsl`` on the config of a daemon that requires CURVE: one line saying so, exit 2
    (they subscribed, heard nothing, and said "is a daemon there?"). With ``--curve`` the bridge hears the daemon."""
    keys, allowed = tmp_path / "keys", tmp_path / "allowed"
    allowed.mkdir()
    for name in ("daemon", "robot"):
        assert run_cli("curve-keys", str(keys), name).returncode == 0
    (allowed / "robot.key").write_bytes((keys / "robot.key").read_bytes())
    cfg = tmp_path / "c.toml"
    endpoint = f"ipc://{tmp_path}/pub"
    cfg.write_text(f'[publish]\nendpoint = "{endpoint}"\ncurve_secret_key_file = "{keys / "daemon.key_secret"}"\n'
                   f'curve_authorized_dir = "{allowed}"\nstatus_interval_s = 0.05\n')
    for command in ("monitor", "lsl", "ros2"):
        res = cli_here(capfd, command, "--config", str(cfg))
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            f"tactiled: error: {cfg}: publish.curve_secret_key_file is set: that daemon serves only subscribers with an authorised "
            "key; pass --curve DAEMON.key MY.key_secret (tactiled curve-keys makes a pair, whose .key goes into "
            "publish.curve_authorized_dir)"], (command, res.stderr)
    proc = subprocess.Popen(tactiled_cmd("run", "--config", str(cfg), "--port", str(tmp_path / "none"), "--no-model"),
                            stderr=subprocess.PIPE, text=True)
    try:
        sink, stop = _Statuses(), threading.Event()
        bridge = threading.Thread(target=run_bridge, args=(endpoint, sink, stop, "fingertip0"),
                                  kwargs={"curve": (str(keys / "daemon.key"), str(keys / "robot.key_secret"))})
        bridge.start()
        try:
            wait_for(lambda: sink.got.wait(1.0), 30, "a status through CURVE")
        finally:
            stop.set()
            bridge.join(30)
        assert sink.statuses and sink.statuses[0].sensor == "fingertip0"
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


def test_a_bridge_waiting_on_a_socket_nobody_binds_names_the_ones_that_are_there(tmp_path: Path) -> None:
    """``tactiled lsl --sensor-id nosuch`` without ``--connect`` waits on ``<runtime folder>/nosuch.sock``, which no daemon
    binds (an outside audit: it waited for ever, saying only "is a daemon there?"); its waiting line names the sockets that
    folder and the service's folder hold."""
    import socket

    from tactiled.apps.bridges import sockets_beside

    service = tmp_path / "run"  # stands for /run/tactiled, where the systemd unit's daemons bind
    service.mkdir()
    with socket.socket(socket.AF_UNIX) as bound, socket.socket(socket.AF_UNIX) as served:
        bound.bind(str(tmp_path / "fingertip0.sock"))
        served.bind(str(service / "arm.sock"))
        assert sockets_beside(f"ipc://{tmp_path}/nosuch.sock", service) == \
            f"; no socket there yet, and {tmp_path / 'fingertip0.sock'}, {service / 'arm.sock'} are: another --sensor-id or --connect?"
        assert sockets_beside(f"ipc://{tmp_path}/fingertip0.sock", service) == "" and sockets_beside("tcp://127.0.0.1:7350") == ""
    assert sockets_beside(f"ipc://{tmp_path}/empty/x.sock", tmp_path / "none") == "; no socket there yet"


def test_a_missing_curve_certificate_and_a_shadow_without_a_model_are_one_line_each(tmp_path: Path,
                                                                                    capfd: pytest.CaptureFixture[str]) -> None:
    """``--curve`` naming a file that is not there: one line, exit 2, for the monitor and the bridges alike (it was a
    traceback from the client library). ``run --no-model`` with a config's ``model.shadow``: no shadow (check-config
    --no-model says such a config is fine for it), and ``--shadow`` with ``--no-model`` is refused (a review)."""
    for command in ("monitor", "lsl", "ros2"):
        res = cli_here(capfd, command, "--curve", str(tmp_path / "d.key"), str(tmp_path / "me.key_secret"), "--connect", f"ipc://{tmp_path}/x")
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            f"tactiled: error: --curve {tmp_path / 'd.key'}: no such certificate file (tactiled curve-keys makes them)"], res.stderr
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[model]\nshadow = "{tmp_path / "gone.npz"}"\n')
    res = cli_here(capfd, "check-config", str(cfg), "--no-model")
    assert res.returncode == 0, res.stderr
    res = run_cli("run", "--config", str(cfg), "--no-model", "--port", str(tmp_path / "none"), "--no-wait")
    assert res.returncode == 2 and "model.shadow" not in res.stderr and "no such serial device" in res.stderr, res.stderr
    res = run_cli("run", "--no-model", "--shadow", str(tmp_path / "gone.npz"), "--port", str(tmp_path / "none"), "--no-wait")
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "tactiled: error: --shadow runs a candidate beside the live model: not with --no-model"], res.stderr
