"""Defects an audit found in the live side (config, control socket, daemon, monitor, demo), each pinned by a check."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tactiled.config import parse_config
from tactiled.errors import ConfigError
from tests.conftest import run_cli


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
