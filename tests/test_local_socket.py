"""The default endpoint: a local ipc socket named for the sensor, found by subscribers, never taken over by a second daemon."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import pytest
from tactiled_client import BlockingSubscriber, Status, local_endpoint

from tactiled.config import Config
from tactiled.errors import ConfigError
from tactiled.service.publish import Publisher, bind_address
from tests.conftest import tactiled_cmd, wait_for


def test_a_daemon_binds_its_sensors_socket_and_a_subscriber_finds_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TACTILED_RUNTIME_DIR", str(tmp_path / "run"))
    master, slave = os.openpty()
    port = os.ttyname(slave)
    proc = subprocess.Popen(tactiled_cmd("run", "--port", port, "--sensor-id", "left"), stderr=subprocess.PIPE, text=True)
    try:
        sock = tmp_path / "run" / "left.sock"
        assert local_endpoint("left") == f"ipc://{sock}"
        with BlockingSubscriber(local_endpoint("left"), topics=["status"], timeout=30) as sub:
            wait_for(lambda: isinstance(sub.receive(), Status), timeout=30, what="a status on the default socket")
        assert stat.S_IMODE(sock.stat().st_mode) == 0o660 and stat.S_IMODE(sock.parent.stat().st_mode) == 0o750
        # a second daemon of the same sensor: one line, exit 2, the first keeps its socket
        second = subprocess.run(tactiled_cmd("run", "--port", port, "--sensor-id", "left"), capture_output=True, text=True, timeout=60)
        assert second.returncode == 2 and "another process already publishes on" in second.stderr, second.stderr
        assert len(second.stderr.strip().splitlines()) == 1 and proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(30)
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""


def test_a_stale_socket_is_replaced_and_auto_is_local(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TACTILED_RUNTIME_DIR", str(tmp_path))
    import socket

    stale = tmp_path / "s1.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.bind(str(stale))  # bound, never listening: what a killed daemon leaves
    assert bind_address("auto", "s1") == f"ipc://{stale}"
    pub = Publisher(Config().publish, sensor="s1")
    try:
        with pytest.raises(ConfigError, match="another process already publishes"):
            Publisher(Config().publish, sensor="s1")
    finally:
        pub.close()
    assert Config().publish.endpoint == "auto"


def test_a_controller_started_before_the_system_daemon_waits_on_the_services_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """At boot a robot controller may start before tactiled@<sensor>: no socket exists yet, and local_endpoint chose this
    environment's (/tmp/tactiled-<uid>), where no daemon would ever bind (an outside audit heard nothing while the service
    published). With the service configured (/etc/tactiled/<sensor>.toml) it is the service's socket, and the subscriber
    hears the daemon once it starts there."""
    import tactiled_client.endpoints as ep

    run, etc = tmp_path / "run", tmp_path / "etc"
    monkeypatch.setattr(ep, "SYSTEM_DIR", run)
    monkeypatch.setattr(ep, "SYSTEM_CONFIG_DIR", etc)
    for var in ("TACTILED_RUNTIME_DIR", "RUNTIME_DIRECTORY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "user"))
    own = f"ipc://{tmp_path}/user/tactiled/boot.sock"
    assert local_endpoint("boot") == own  # no service here: this environment's, where a daemon of this user would bind
    etc.mkdir()
    (etc / "boot.toml").write_text("")
    endpoint = local_endpoint("boot")
    assert endpoint == f"ipc://{run}/boot.sock"
    master, slave = os.openpty()
    with BlockingSubscriber(endpoint, topics=["status"], timeout=30) as sub:  # before the daemon, as at boot
        env = {**os.environ, "RUNTIME_DIRECTORY": str(run)}  # what systemd sets for the unit
        proc = subprocess.Popen(tactiled_cmd("run", "--port", os.ttyname(slave), "--sensor-id", "boot"), stderr=subprocess.PIPE, text=True, env=env)
        try:
            wait_for(lambda: isinstance(sub.receive(), Status), timeout=30, what="a status from the service's socket")
        finally:
            proc.terminate()
            proc.wait(30)
            os.close(master)
            os.close(slave)
    assert local_endpoint("boot") == f"ipc://{run}/boot.sock"  # its config stays
    # another sensor, with no service here, while /run/tactiled (the folder systemd made for boot's) exists: this environment's
    assert run.is_dir() and local_endpoint("bench1") == f"ipc://{tmp_path}/user/tactiled/bench1.sock"
