"""export: a recording's ``disconnected`` marks (where the host lost the sensor's port) reach the MCAP file, one message
per mark on ``/tactiled/<id>/disconnected``, in both profiles."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from tactiled.files.recording import save_recording
from tests.conftest import lossy_recording, run_cli

ORIGIN = 1767323045  # 2026-01-02T03:04:05Z: the recording's start, host time
FIRST = 123_456


def _marked(tmp_path: Path) -> tuple[Path, list[int], float]:
    """A recording saved with three marks (the last at its end); returns its path, the marks' positions and fs."""
    rec = lossy_recording(FIRST, meta={"recorded_at": "2026-01-02T03:04:05+0000"}, slides=1, lost=((1000, 37),))
    marks = [1037, rec.samples.shape[0] // 2, rec.samples.shape[0]]  # after the lost range, mid-file, and at the very end
    rec.disconnected = np.array(marks, dtype=np.int64)
    save_recording(tmp_path / "r.npz", rec)
    return tmp_path / "r.npz", marks, rec.fs


def test_export_json_carries_each_disconnection_with_its_index_and_time(tmp_path: Path) -> None:
    path, marks, fs = _marked(tmp_path)
    res = run_cli("export", str(path), "-o", str(tmp_path / "r.mcap"), "--no-model")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().endswith(", 3 disconnections"), res.stdout
    with open(tmp_path / "r.mcap", "rb") as fh:
        got = [(schema.name if schema else "", channel.message_encoding, message.log_time, json.loads(message.data))
               for schema, channel, message in make_reader(fh).iter_messages(topics=["/tactiled/fingertip0/disconnected"])]
    assert [g[3] for g in got] == [{"index": FIRST + p, "t": (FIRST + p) / fs} for p in marks]  # absolute indices, as every channel
    assert [g[2] for g in got] == [ORIGIN * 10**9 + round(p * 1e9 / fs) for p in marks]  # host time of the mark's sample
    assert {(g[0], g[1]) for g in got} == {("tactiled.Disconnected", "json")}


def test_export_ros2_carries_each_disconnection(tmp_path: Path) -> None:
    rosbag2 = importlib.import_module("rosbags.rosbag2")  # in the dev extras: a missing one fails
    typesys = importlib.import_module("rosbags.typesys")
    path, marks, fs = _marked(tmp_path)
    res = run_cli("export", str(path), "-o", str(tmp_path / "r.mcap"), "--no-model", "--profile", "ros2")
    assert res.returncode == 0, res.stderr
    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    with rosbag2.Reader(tmp_path / "r.mcap") as reader:
        conns = [c for c in reader.connections if c.topic == "/tactiled/fingertip0/disconnected"]
        assert [c.msgtype for c in conns] == ["std_msgs/msg/String"]
        got = [(t, json.loads(ts.deserialize_cdr(raw, conn.msgtype).data)) for conn, t, raw in reader.messages(connections=conns)]
    assert got == [(ORIGIN * 10**9 + round(p * 1e9 / fs), {"index": FIRST + p, "t": (FIRST + p) / fs}) for p in marks]


def test_replay_of_the_export_reads_the_marks_back(tmp_path: Path) -> None:
    """`tactiled replay rec.mcap` sees the recording the `.npz` held, marks included (a slide ends at each, as it did live)."""
    from tactiled.files.mcap_read import load_mcap_recording

    path, marks, _ = _marked(tmp_path)
    res = run_cli("export", str(path), "-o", str(tmp_path / "r.mcap"), "--no-model")
    assert res.returncode == 0, res.stderr
    back = load_mcap_recording(tmp_path / "r.mcap")
    assert back.disconnected.tolist() == marks
    assert back.first_index == FIRST
