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
