"""The bridges' own logic without any middleware: what run_bridge says and refuses, and the ROS 2 message layouts.

A real PUB socket on ipc feeds :func:`run_bridge` with a sink that records, and the LSL sink is fed
messages directly with a fake pylsl (outlets that keep what was pushed); nothing here opens an LSL
outlet or a DDS participant, so it runs outside a network namespace.
"""

from __future__ import annotations

import importlib
import json
import threading
import types
from pathlib import Path

import numpy as np
from tactiled_client import Samples, Status, schema

from tactiled.apps.bridges import StreamMeta, lost_ranges, run_bridge
from tactiled.apps.bridges.lsl import LslSink
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


class FakeXml:
    """pylsl's XMLElement, enough for a stream description."""

    def append_child(self, name: str) -> FakeXml:
        return self

    def append_child_value(self, name: str, value: str) -> FakeXml:
        return self


class FakeInfo:
    def __init__(self, *args: object) -> None:
        self.args = args

    def desc(self) -> FakeXml:
        return FakeXml()


class FakeOutlet:
    """An LSL outlet that keeps what was pushed: rows (float32) with their stamps, and string samples with theirs."""

    def __init__(self, info: FakeInfo, chunk_size: int = 0, max_buffered: int = 360) -> None:
        self.info, self.rows, self.stamps, self.strings = info, [np.zeros((0, int(str(info.args[2]))), np.float32)], [], []

    def push_chunk(self, x: np.ndarray, timestamp: float | list[float] = 0.0) -> None:
        assert isinstance(timestamp, list) and len(timestamp) == len(x)
        self.rows.append(np.asarray(x, np.float32))
        self.stamps += timestamp

    def push_sample(self, x: list[str], timestamp: float = 0.0) -> None:
        self.strings.append((json.loads(x[0]), timestamp))


FAKE_LSL = types.SimpleNamespace(StreamInfo=FakeInfo, StreamOutlet=FakeOutlet, IRREGULAR_RATE=0.0)
FS = 1000.0


def fake_sink(nan_lost: bool = True, nan_max_s: float = 30.0) -> LslSink:
    return LslSink(StreamMeta("tip7", 2, FS, 0.5), nan_lost=nan_lost, nan_max_s=nan_max_s, lsl=FAKE_LSL)


def batch(index: int, n: int = 100, lost_before: int = 0, step_s: float = 0.0, step_at: int = 0) -> Samples:
    """A samples message with the host times of a mapping that steps forward by ``step_s`` from index ``step_at`` on."""
    counts = np.ones((n, 2), dtype=np.int16)
    return schema.samples("tip7", index, counts.astype("<i2").tobytes(), n, 2, fs=FS, volts_per_count=0.5, lost=[[10, 5]],
                          lost_before=lost_before, to_host=lambda i: (50.0 + i / FS + (step_s if i >= step_at else 0.0), 1.7e9 + i / FS))


def pushed(sink: LslSink) -> tuple[np.ndarray, np.ndarray, list[dict[str, object]]]:
    raw, marks = sink.raw, sink.markers
    return np.concatenate(raw.rows), np.array(raw.stamps), [m for m, _ in marks.strings]


def test_nan_lost_fills_a_gap_the_daemon_only_counts_so_the_stream_stays_regular() -> None:
    sink = fake_sink()
    sink.samples(batch(0))
    sink.samples(batch(100 + 1012, lost_before=1012, step_s=0.15, step_at=1112))  # an unplug of 1.012 s; the mapping stepped forward
    rows, stamps, markers = pushed(sink)
    assert len(rows) == 100 + 1012 + 100 and np.isnan(rows).any(axis=1).sum() == 1012 + 5 + 5
    assert np.isnan(rows[100:1112]).all() and np.diff(stamps).min() > 0 and np.diff(stamps).max() < 1.2 / FS  # no hole: every row stamped
    assert abs(stamps[100] - stamps[99] - 1 / FS) < 1e-9 and abs(stamps[1112] - (50.0 + 1112 / FS + 0.15)) < 1e-9
    assert {"event": "lost", "index": 100, "count": 1012, "filled": True} in markers
    plain = fake_sink(nan_lost=False)
    plain.samples(batch(0))
    plain.samples(batch(1112, lost_before=1012))
    rows, _, markers = pushed(plain)
    assert len(rows) == 190 and not np.isnan(rows).any() and {"event": "lost", "index": 100, "count": 1012, "filled": False} in markers


def test_a_daemon_restart_is_a_loss_marker_nan_filled_when_the_index_carried_on_and_unknown_when_it_went_back() -> None:
    sink = fake_sink()
    sink.samples(batch(0))
    sink.samples(batch(100 + 3900))  # a new daemon: the board's index carried on over 3.9 s, and it says nothing lost (lost_before 0)
    sink.samples(batch(7))  # another one that started the index again
    rows, stamps, markers = pushed(sink)
    lost = [m for m in markers if m["count"] != 5]
    assert lost == [{"event": "lost", "index": 100, "count": 3900, "filled": True},
                    {"event": "lost", "index": None, "count": None, "next": 7, "filled": False}]
    assert len(rows) == 100 + 3900 + 100 + 100 and np.isnan(rows[100:4000]).all() and np.diff(stamps[:4100]).max() < 1.2 / FS
    assert abs(sink.markers.strings[-2][1] - (50.0 + 4100 / FS)) < 1e-9  # the unknown loss stamped where the last rows pushed ended


def test_a_gap_longer_than_nan_max_s_is_only_its_marker() -> None:
    sink = fake_sink(nan_max_s=2.0)
    sink.samples(batch(0))
    sink.samples(batch(100 + 2000, lost_before=2000))  # 2 s: filled
    sink.samples(batch(2200 + 2001, lost_before=2001))  # just over: the marker says so, no rows
    sink.samples(batch(2**40))  # an index jump of hours: no rows (nor an array of them)
    rows, stamps, markers = pushed(sink)
    assert len(rows) == 100 + 2000 + 100 + 100 + 100 and np.diff(stamps).min() > 0
    assert [(m["index"], m["count"], m["filled"]) for m in markers if m["count"] != 5] == [(100, 2000, True), (2200, 2001, False),
                                                                                           (4301, 2**40 - 4301, False)]


def test_a_lost_range_across_messages_is_one_marker() -> None:
    """An outside audit: a range of 500 lost samples split by a samples message's end gave two markers (400 and 100), so a
    tool counting lost ranges in the XDF overcounted. One marker, stamped at its first sample, once the range ends; a range
    that ends with a message and is not continued is pushed with the next message, or at close."""
    def lost_batch(index: int, lost: list[list[int]], n: int = 100) -> Samples:
        counts = np.ones((n, 2), dtype=np.int16)
        return schema.samples("tip7", index, counts.astype("<i2").tobytes(), n, 2, fs=FS, volts_per_count=0.5, lost=lost,
                              to_host=lambda i: (50.0 + i / FS, 1.7e9 + i / FS))

    sink = fake_sink(nan_lost=False)
    sink.samples(lost_batch(0, [[60, 40]]))  # reaches the end
    sink.samples(lost_batch(100, [[0, 100]]))  # a whole message lost
    sink.samples(lost_batch(200, [[0, 20], [50, 10]]))  # goes on, then a range of its own
    sink.samples(lost_batch(300, [[90, 10]]))  # reaches the end, then the next message starts intact
    sink.samples(lost_batch(400, []))
    sink.samples(lost_batch(500, [[95, 5]]))  # open when the bridge stops
    outlet = sink.markers
    sink.close()
    assert [(m["index"], m["count"], t) for m, t in outlet.strings if m["event"] == "lost"] == [
        (60, 160, 50.06), (250, 10, 50.25), (390, 10, 50.39), (595, 5, 50.595)]
    # a gap between messages (lost_before) that the next message's first rows go on with, also after an open range: one
    gap = fake_sink(nan_lost=False)
    gap.samples(lost_batch(0, [[90, 10]]))
    counts = np.ones((100, 2), dtype=np.int16)
    gap.samples(schema.samples("tip7", 200, counts.astype("<i2").tobytes(), 100, 2, fs=FS, volts_per_count=0.5, lost=[[0, 20]],
                               lost_before=100, to_host=lambda i: (50.0 + i / FS, 1.7e9 + i / FS)))
    outlet = gap.markers
    gap.close()
    assert [(m["index"], m["count"]) for m, _ in outlet.strings if m["event"] == "lost"] == [(90, 130)]
