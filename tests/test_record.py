"""`tactiled record` end to end from a virtual board on a real pty, with faults and an unplug."""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path

import numpy as np

from tactiled.recording import load_recording
from tactiled.sensor_model import SensorModel, SimParams, default_surfaces
from tactiled.virtualboard import VirtualBoard, read_log
from tests.conftest import run_cli, tactiled_cmd


def test_record_keeps_every_intact_sample_through_faults_and_unplug(tmp_path: Path) -> None:
    params = SimParams()
    link = str(tmp_path / "tactile0")
    log_path = tmp_path / "board.jsonl"
    first = 2**32 - 30_000  # the 32-bit index wraps 1.5 s in
    with open(log_path, "w") as log:
        board = VirtualBoard(SensorModel(params, seed=3), default_surfaces()[:3], link=link, speed=2.0, corrupt=0.01,
                             drop=0.005, garbage=0.01, unplug_at=[1.0], unplug_s=0.2, seed=3, log=log, first_index=first)
        board.open()
        stop = threading.Event()
        out = tmp_path / "rec.npz"
        proc = subprocess.Popen(tactiled_cmd("record", "--port", link, "--seconds", "2.5", "-o", str(out)),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        thread = threading.Thread(target=board.run, args=(stop,), daemon=True)
        thread.start()
        try:
            stdout, stderr = proc.communicate(timeout=60)
        finally:
            stop.set()
            thread.join(10)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    events = read_log(log_path)
    n = rec.samples.shape[0]
    assert n == 50_000
    assert "1 reconnects" in stdout
    # the expected stream: regenerate the same seeded samples
    expected = SensorModel(params, seed=3)
    start = rec.first_index - first
    expected.schedule_random(default_surfaces()[:3], start + n)
    if start:
        expected.read(start)
    truth = expected.read(n)
    bad = np.zeros(n, dtype=bool)
    for e in events:
        if e["event"] in ("drop", "corrupt", "overrun", "unplug"):
            lo = e["index"] - rec.first_index
            hi = lo + (e.get("count") or 20)
            if e["event"] == "unplug":
                # down 0.2 s; then until the reader's backoff reopens the port the new pty's ~4 KB
                # buffer overflows (a real device is no better): bounded by one second
                hi = lo + round(1.0 * params.fs)
            if e["event"] == "unplug":
                lo -= round(0.05 * params.fs)  # frames still unread in the pty when it closed (one read period)
            bad[max(lo, 0):max(min(hi, n), 0)] = True
    valid = rec.valid_mask()
    # every intact sample the board sent is present at its index
    assert np.array_equal(rec.samples[valid], truth[valid])
    # every sample not received is listed as lost, and only samples the board did not deliver intact
    assert not np.any(~valid & ~bad)
    assert rec.lost[:, 1].sum() == int((~valid).sum()) > 0
    assert np.all(rec.samples[~valid] == 0)
    assert any(e["event"] == "unplug" for e in events) and any(e["event"] == "corrupt" for e in events)


def test_record_missing_port_is_one_line_and_no_file(tmp_path: Path) -> None:
    out = tmp_path / "x.npz"
    res = run_cli("record", "--port", str(tmp_path / "nope"), "--seconds", "1", "-o", str(out))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"tactiled: error: {tmp_path / 'nope'}: no such serial device"]
    assert list(tmp_path.iterdir()) == []


def test_record_bad_config_value(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sensor]\nchannels = 0\n")
    res = run_cli("record", "--config", str(cfg), "--port", "/dev/null", "--seconds", "1", "-o", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert "sensor.channels: must be in 1..8" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.npz").exists()


def test_record_ctrl_c_saves_what_was_captured(tmp_path: Path) -> None:
    link = str(tmp_path / "dev")
    board = VirtualBoard(SensorModel(SimParams(), seed=1), default_surfaces()[:2], link=link, speed=1.0, seed=1)
    board.open()
    stop = threading.Event()
    thread = threading.Thread(target=board.run, args=(stop,), daemon=True)
    thread.start()
    out = tmp_path / "r.npz"
    proc = subprocess.Popen(tactiled_cmd("-v", "record", "--port", link, "--seconds", "600", "-o", str(out)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        assert "recording" in proc.stderr.readline()
        started = board.sent_samples
        assert board.wait_sent(started + 4000, timeout=20), "board streaming to the recorder"
        proc.send_signal(2)
        _stdout, stderr = proc.communicate(timeout=30)
    finally:
        stop.set()
        thread.join(10)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    assert rec.samples.shape[0] > 0 and rec.samples.shape[1] == 2
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
