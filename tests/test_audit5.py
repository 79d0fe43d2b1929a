"""Defects an outside audit of 2026-11-27 (the seventeenth session) reproduced, each with the test that fails without its mend."""

from __future__ import annotations

import numpy as np


def test_replays_summary_counts_an_untaught_surface_called_unknown_right_as_score_does() -> None:
    """An outside audit: ``replay --model`` said "0 of 3 true slides right" of a surface the model was not taught, each
    slide rightly called unknown, where ``score`` said "called unknown (the right answer)"."""
    from tactiled.core.events import SlideResult
    from tactiled.files.recording import Recording
    from tactiled.run.replay import summary_line

    rec = Recording(np.zeros((30_000, 2), dtype=np.int16), 20_000.0, 1e-4, slide_start=np.array([1000, 11_000, 21_000]),
                    slide_stop=np.array([9000, 19_000, 29_000]), surface=np.array(["felt", "felt", "Ra1.00"]))
    results = [SlideResult(1, 1000, 9000, (1000, 9000), None, "unknown_surface", 0.4, [], {}),
               SlideResult(2, 11_000, 19_000, (11_000, 19_000), "Ra1.00", None, 0.8, [], {}),  # an untaught surface labelled: wrong
               SlideResult(3, 21_000, 29_000, (21_000, 29_000), None, "unknown_surface", 0.4, [], {})]  # a taught one unknown: wrong
    assert summary_line(results, rec, ("Ra1.00", "Ra1.18")).endswith(
        "3 slides, 1 labelled, 2 unknown surface, 1 of 3 true slides right (1 of a surface the model was not taught, called unknown)")
    assert summary_line(results, rec).endswith("0 of 3 true slides right")  # without the model's surfaces: as before


def test_an_ipv6_loopback_endpoint_binds_and_a_client_receives_on_it() -> None:
    """``publish.endpoint = "tcp://[::1]:0"`` passed check-config, then ``run`` failed with "No such device", and a client
    pointed at an IPv6 publisher heard nothing: ZeroMQ sockets are IPv4 only unless told."""
    import socket

    import pytest
    from tactiled_client import BlockingSubscriber, NoData, Status, schema

    from tactiled.config import PublishConfig
    from tactiled.service.publish import Publisher

    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
    except OSError:
        pytest.skip("this host has no IPv6 loopback")
    pub = Publisher(PublishConfig(endpoint="tcp://[::1]:0"))
    try:
        assert pub.endpoint.startswith("tcp://[::1]:")
        with BlockingSubscriber(pub.endpoint, topics=["status"], timeout=0.05) as sub:
            got = None
            for _ in range(400):  # the subscription is in flight for a moment (ZeroMQ's slow joiner): publish until one arrives
                pub.publish(schema.status("fingertip0", state=schema.STATE_IDLE))
                try:
                    got = sub.receive()
                    break
                except NoData:
                    continue
            assert isinstance(got, Status) and got.state == schema.STATE_IDLE
    finally:
        pub.close()


def test_a_clean_stop_removes_the_daemons_ipc_socket_files(tmp_path: object) -> None:
    """After SIGTERM (exit 0) the publish and control sockets' files were left behind: ZeroMQ does not remove them."""
    from pathlib import Path

    from tactiled_client import BlockingSubscriber, Status

    from tests.conftest import board_and_daemon, wait_for

    tmp = Path(str(tmp_path))
    config = tmp / "c.toml"
    config.write_text(f'[control]\nendpoint = "ipc://{tmp}/ctl"\n')
    with board_and_daemon(tmp, "--config", str(config)) as live, BlockingSubscriber(live.endpoint, topics=["status"], timeout=20) as sub:
        wait_for(lambda: isinstance(sub.receive(), Status), timeout=60, what="a status")
        assert (tmp / "pub").is_socket() and (tmp / "ctl").is_socket()
        live.stop()
    assert live.proc.returncode == 0
    assert not (tmp / "pub").exists() and not (tmp / "ctl").exists()


def test_run_names_the_config_file_and_the_missing_folder_of_its_socket(tmp_path: object) -> None:
    """check-config said "c.toml: publish.endpoint: the folder ... does not exist"; run said ZeroMQ's raw text without the file."""
    from pathlib import Path

    from tests.conftest import run_cli

    tmp = Path(str(tmp_path))
    config = tmp / "c.toml"
    for key, section in (("publish.endpoint", "publish"), ("control.endpoint", "control")):
        config.write_text(f'[{section}]\nendpoint = "ipc://{tmp}/nope/{section}.sock"\n')
        res = run_cli("run", "--config", str(config), "--port", str(tmp / "no-port"), timeout=60)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert f"{config}: {key}: cannot bind" in res.stderr and f"the folder {tmp}/nope does not exist" in res.stderr, res.stderr


def test_the_monitor_says_it_needs_a_terminal_when_its_output_is_not_one(tmp_path: object) -> None:
    """Redirected to a file, ``tactiled monitor`` wrote nothing for as long as it ran, without a word."""
    from tests.conftest import run_cli

    res = run_cli("monitor", "--connect", f"ipc://{tmp_path}/pub", timeout=60)  # its stdout a pipe
    assert res.returncode == 2 and res.stdout == "" and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "not a terminal" in res.stderr and "tactiled_client record" in res.stderr
