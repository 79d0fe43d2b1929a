"""The bridges' own logic without any middleware: what run_bridge says and refuses, and the ROS 2 message layouts.

A real PUB socket on ipc feeds :func:`run_bridge` with a sink that records; nothing here opens
an LSL outlet or a DDS participant, so it runs outside a network namespace.
"""

from __future__ import annotations

import importlib
import json
import threading
from pathlib import Path

import numpy as np
from tactiled_client import Status, schema

from tactiled.apps.bridges import lost_ranges, run_bridge
from tactiled.apps.bridges.ros2 import node_name, samples_table, status_values, table_dtype
from tactiled.config import PublishConfig
from tactiled.errors import TactiledError
from tactiled.service.publish import Publisher
from tests.conftest import BridgeSink, run_cli


class Said(list[str]):
    """The lines a bridge said; ``spoke`` is set at each."""

    def __init__(self) -> None:
        super().__init__()
        self.spoke = threading.Event()

    def __call__(self, line: str) -> None:
        self.append(line)
        self.spoke.set()


def bridge_on(endpoint: str, sensor: str, patience_s: float) -> tuple[threading.Thread, BridgeSink, threading.Event, Said, list[BaseException]]:
    sink, stop, said, errors = BridgeSink(), threading.Event(), Said(), []

    def run() -> None:
        try:
            run_bridge(endpoint, sink, stop, sensor, poll_s=0.05, patience_s=patience_s, say=said, raw_name="raw outlet")
        except TactiledError as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, sink, stop, said, errors


def test_a_sensor_id_the_daemon_does_not_publish_is_one_error(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/pub"
    pub = Publisher(PublishConfig(endpoint=endpoint))
    thread, sink, stop, _said, errors = bridge_on(endpoint, "wrong", patience_s=0.5)
    try:
        while thread.is_alive():
            pub.publish(schema.status("fingertip0", state=schema.STATE_IDLE))
            thread.join(0.05)  # the daemon's status period while the bridge makes up its mind; it ends by itself
    finally:
        stop.set()
        pub.close()
    assert len(errors) == 1 and "publishes sensor fingertip0, not 'wrong'" in str(errors[0]) and "\n" not in str(errors[0])
    assert sink.got == [] and sink.closed.is_set()


def test_status_without_samples_says_why_the_raw_stream_stays_empty_and_silence_is_said_once(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/pub"
    thread, sink, stop, said, errors = bridge_on(endpoint, "tip7", patience_s=0.3)
    assert said.spoke.wait(10) and "nothing from" in said[0]  # nothing published yet
    pub = Publisher(PublishConfig(endpoint=endpoint))
    try:
        while not any("no samples" in s for s in said):
            pub.publish(schema.status("tip7", state=schema.STATE_IDLE))
            thread.join(0.05)  # the daemon's status period until the bridge speaks
            assert thread.is_alive()
    finally:
        stop.set()
        thread.join(10)
        pub.close()
    assert not errors and sum("nothing from" in s for s in said) == 1
    line = next(s for s in said if "no samples" in s)
    assert "raw outlet" in line and "--samples" in line and all(isinstance(m, Status) and m.sensor == "tip7" for m in sink.got)


def test_ros_args_ros_does_not_take_are_one_line_exit_2() -> None:
    importlib.import_module("rclpy")  # in the dev extras: a missing one fails
    res = run_cli("ros2", "--connect", "ipc:///nonexistent/pub", "--ros-args", "--no-such-flag", timeout=60)
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0 and "--ros-args --no-such-flag" in res.stderr


def test_samples_table_is_one_row_per_sample_with_its_index_time_and_nan_for_lost() -> None:
    counts = np.arange(20, dtype=np.int16).reshape(10, 2)
    msg = schema.samples("s", 2**40, counts.astype("<i2").tobytes(), 10, 2, fs=20_000.0, volts_per_count=0.5, lost=[[3, 2]],
                         to_host=lambda i: (5.0, 1.7e9 + (i - 2**40) / 20_000.0), fs_clock=19_990.0)
    data, unix, dense = samples_table(msg)
    rows = np.frombuffer(data, dtype=table_dtype(2))
    assert table_dtype(2).itemsize == 4 * 2 + 12 and unix == 1.7e9 and not dense
    assert rows["index"].tolist() == [2**40 + k for k in range(10)]
    assert np.allclose(rows["t"], np.arange(10) / 19_990.0)
    film = np.column_stack([rows["film1"], rows["film2"]])
    assert np.isnan(film[3:5]).all() and np.array_equal(np.delete(film, [3, 4], axis=0), np.delete(counts * 0.5, [3, 4], axis=0))
    assert lost_ranges(msg) == [(2**40 + 3, 2)]
    assert lost_ranges(schema.samples("s", 500, b"", 0, 2, fs=1.0, volts_per_count=1.0, lost_before=100)) == [(400, 100)]


def test_status_values_are_json_not_python_reprs() -> None:
    values = dict(status_values(schema.status("tip7", state="idle", level=[0.5, 0.25], model="abc")))
    assert values["state"] == "idle" and values["model"] == "abc" and values["level"] == "[0.5, 0.25]"
    assert values["clock_mono"] == "null" and json.loads(values["samples"]) == 0
    assert node_name("tip-7.a") == "tactiled_tip_7_a"
