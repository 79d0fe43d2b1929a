"""export --profile ros2: a ROS 2 bag in one MCAP file, read back with rosbags (its reader and CDR), as ros2 bag play would.

``ros2 bag play`` itself is not installable from PyPI (rosbag2 has no wheel), so rosbags is the reader here.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import numpy as np

from tactiled.apps.bridges.ros2 import table_dtype
from tactiled.files.recording import save_recording
from tactiled.sim.physics import SimParams
from tests.conftest import lossy_recording, run_cli


def test_export_profile_ros2_reads_back_with_rosbags(tmp_path: Path) -> None:
    rosbag2 = importlib.import_module("rosbags.rosbag2")  # in the dev extras: a missing one fails
    typesys = importlib.import_module("rosbags.typesys")  # in the dev extras: a missing one fails
    rec = lossy_recording(10_000, meta={"recorded_at": "2026-01-02T03:04:05+0000"})
    params, samples = SimParams(), rec.samples
    save_recording(tmp_path / "r.npz", rec)
    res = run_cli("export", str(tmp_path / "r.npz"), "-o", str(tmp_path / "r.mcap"), "--profile", "ros2")
    assert res.returncode == 0, res.stderr
    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    got: dict[str, list[tuple[int, object]]] = {}
    with rosbag2.Reader(tmp_path / "r.mcap") as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            got.setdefault(conn.topic, []).append((t, ts.deserialize_cdr(raw, conn.msgtype)))
    assert types == {"/tactiled/fingertip0/samples": "sensor_msgs/msg/PointCloud2", "/tactiled/fingertip0/roughness": "std_msgs/msg/String",
                     "/tactiled/fingertip0/roughness/json": "std_msgs/msg/String", "/tactiled/fingertip0/slides": "std_msgs/msg/String"}
    origin = 1767323045  # 2026-01-02T03:04:05Z: the recording's start, host time
    clouds = [m for _, m in got["/tactiled/fingertip0/samples"]]
    rows = np.concatenate([np.frombuffer(m.data.tobytes(), dtype=table_dtype(2)) for m in clouds])  # type: ignore[attr-defined]
    assert rows["index"].tolist() == list(range(10_000, 10_000 + len(samples)))
    film = np.column_stack([rows["film1"], rows["film2"]])
    valid = rec.valid_mask()
    assert np.isnan(film[~valid]).all()
    assert np.array_equal(np.rint(film[valid] / params.volts_per_count).astype(np.int16), samples[valid])  # every intact sample, exactly
    first = clouds[1]
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (origin, round(500 / params.fs * 1e9))  # type: ignore[attr-defined]
    assert got["/tactiled/fingertip0/samples"][1][0] == origin * 10**9 + round(500 / params.fs * 1e9)  # log time: host ns
    finals = [json.loads(m.data) for _, m in got["/tactiled/fingertip0/roughness/json"] if json.loads(m.data)["final"]]  # type: ignore[attr-defined]
    assert [m.data for _, m in got["/tactiled/fingertip0/roughness"]] == [f["label"] or "" for f in finals]  # type: ignore[attr-defined]
    assert len(finals) == 3 and all(f["start"] >= 10_000 for f in finals)
    slides = [json.loads(m.data) for _, m in got["/tactiled/fingertip0/slides"]]  # type: ignore[attr-defined]
    assert [(s["start"] - 10_000, s["stop"] - 10_000, s["surface"]) for s in slides] == rec.slides()
