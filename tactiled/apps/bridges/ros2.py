"""ROS 2 bridge (``tactiled ros2``, extra ``tactiled[ros2]``: the ros-jazzy-* wheels, no colcon build).

One node, ``tactiled_<id>`` (remap with ``__node``), standard message types only. Topic names are
relative, so ``--ros-args -r __ns:=/robot1`` moves them all and ``-r <name>:=<other>`` renames one;
``/diagnostics`` is the ROS convention and stays absolute. For sensor ``<id>``:

- ``tactiled/<id>/samples`` sensor_msgs/PointCloud2 used as a typed table, one message per raw
  batch (no x, y, z: not for rviz). ``header.stamp`` is the host (unix) time of the batch's
  first row from the daemon's clock mapping (docs/messages.md; the node's clock now when the
  daemon gives none), ``header.frame_id`` the ``frame_id`` parameter (default: the sensor id).
  ``height`` 1, ``width`` n rows, one row per sample with fields ``film1`` … ``filmC`` (float32,
  volts, NaN when lost: ``is_dense`` false), ``t`` (float32, s after ``header.stamp``) and
  ``index`` (float64, the sensor sample index, exact below 2**53). :func:`tactiled.rostable.table_dtype` is its numpy
  dtype: ``np.frombuffer(msg.data, table_dtype(C))``. QoS: sensor data (best effort, depth 5).
- ``tactiled/<id>/roughness`` std_msgs/String: the final label ("" when abstaining). Reliable, depth 10.
  A bare string names no slide, so it cannot say that a label was withdrawn: ``roughness/json`` does.
- ``tactiled/<id>/roughness/json`` std_msgs/String: every roughness message (final and
  provisional) as the JSON object of docs/messages.md (host times in ``start_unix`` …), and every
  slide message ``resumed`` as its JSON object (``"type": "slide"``: the final label of that
  ``slide_id`` just published is withdrawn; the slide's real final label follows). Reliable, depth 10.
- ``tactiled/<id>/status`` std_msgs/String: every status message as JSON. Reliable, depth 10.
- ``/diagnostics`` diagnostic_msgs/DiagnosticArray, stamped now: the status as a DiagnosticStatus
  (OK connected/idle/sliding, ERROR disconnected, STALE stopping), every field a key/value whose
  value is the string itself or JSON (``null``, ``[0.01, 0.02]``). Reliable, depth 10.

Parameters (``-p name:=value``, or a params file): ``endpoint`` (the daemon's, default
``--connect``), ``sensor_id`` (default ``--sensor-id``) and ``frame_id``.
"""

from __future__ import annotations

import array
import contextlib
import json
import re
import threading
from typing import Any

import numpy as np
from tactiled_client import Roughness, Samples, Slide, Status, schema

from tactiled.apps.bridges import json_value, volts
from tactiled.errors import TactiledError
from tactiled.extras import need
from tactiled.rostable import field_names, table_dtype

__all__ = ["Ros2Sink", "node_name", "samples_table", "stamp", "status_values", "table_dtype"]

LEVEL = {schema.STATE_DISCONNECTED: 2, schema.STATE_STOPPING: 3}  # DiagnosticStatus ERROR, STALE; others OK


def stamp(unix: float | None, now: Any) -> Any:
    """builtin_interfaces/Time of a unix time (``now``, a Time, when None)."""
    if unix is None:
        return now
    time_cls = type(now)
    sec = int(unix // 1)
    return time_cls(sec=sec, nanosec=min(round((unix - sec) * 1e9), 999_999_999))


def samples_table(msg: Samples) -> tuple[bytes, float | None, bool]:
    """(rows as bytes of :func:`table_dtype`, unix time of row 0 or None, no row lost) of a samples message."""
    v, valid, _ = volts(msg)
    assert isinstance(v, np.ndarray) and isinstance(valid, np.ndarray)
    rows = np.zeros(msg.n, dtype=table_dtype(msg.channels))
    for k in range(msg.channels):
        rows[f"film{k + 1}"] = np.where(valid, v[:, k], np.float32(np.nan))
    rows["t"] = np.arange(msg.n) / (msg.fs_clock or msg.fs)
    rows["index"] = msg.index + np.arange(msg.n, dtype=np.float64)
    return rows.tobytes(), msg.index_unix, bool(valid.all())


def status_values(msg: Status) -> list[tuple[str, str]]:
    """(key, value) of every status field for a DiagnosticStatus: strings as they are, the rest as JSON."""
    return [(k, json_value(v)) for k, v in msg.to_map().items()]


def node_name(sensor: str) -> str:
    """``tactiled_<id>`` with every character a ROS name may not hold replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", f"tactiled_{sensor}")


class Ros2Sink:
    """One rclpy node spun in a thread (parameters, introspection); publishing needs no spinning."""

    def __init__(self, sensor: str, endpoint: str = "", ros_args: list[str] | None = None) -> None:
        """``ros_args``: what followed ``--ros-args`` on the command line (remapping, namespace, parameters)."""
        self.rclpy: Any = need("rclpy", "ros2")
        std = need("std_msgs.msg", "ros2")
        diag = need("diagnostic_msgs.msg", "ros2")
        sensor_msgs = need("sensor_msgs.msg", "ros2")
        qos = need("rclpy.qos", "ros2")
        executors = need("rclpy.executors", "ros2")
        self.String = std.String
        self.PointCloud2, self.PointField = sensor_msgs.PointCloud2, sensor_msgs.PointField
        self.DiagnosticStatus, self.DiagnosticArray, self.KeyValue = diag.DiagnosticStatus, diag.DiagnosticArray, diag.KeyValue
        self._owns_rclpy = not self.rclpy.ok()
        if self._owns_rclpy:
            signals = need("rclpy.signals", "ros2")
            args = ["tactiled", "--ros-args", *ros_args] if ros_args else None
            bad = need("rclpy._rclpy_pybind11", "ros2")
            try:
                self.rclpy.init(args=args, signal_handler_options=signals.SignalHandlerOptions.NO)  # SIGINT/SIGTERM stop the bridge
            except (bad.UnknownROSArgsError, bad.RCLInvalidROSArgsError) as exc:
                raise TactiledError(f"--ros-args {' '.join(ros_args or [])}: ROS does not take them: {str(exc).splitlines()[0]}") from None
        self.node = self.rclpy.create_node(node_name(sensor))
        self.endpoint = str(self.node.declare_parameter("endpoint", endpoint).value)
        self.sensor = str(self.node.declare_parameter("sensor_id", sensor).value)
        self.frame_id = str(self.node.declare_parameter("frame_id", self.sensor).value)
        base = f"tactiled/{self.sensor}"
        self.pub_label = self.node.create_publisher(self.String, f"{base}/roughness", 10)
        self.pub_json = self.node.create_publisher(self.String, f"{base}/roughness/json", 10)
        self.pub_status = self.node.create_publisher(self.String, f"{base}/status", 10)
        self.pub_diag = self.node.create_publisher(self.DiagnosticArray, "/diagnostics", 10)
        self.pub_samples = self.node.create_publisher(self.PointCloud2, f"{base}/samples", qos.qos_profile_sensor_data)
        self._fields: list[Any] = []
        self.executor = executors.SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._spin = threading.Thread(target=self._spin_until_shutdown, name="ros2-spin", daemon=True)
        self._spin.start()

    def _spin_until_shutdown(self) -> None:
        ex = need("rclpy.executors", "ros2")
        with contextlib.suppress(ex.ExternalShutdownException):
            self.executor.spin()

    def _now(self) -> Any:
        return self.node.get_clock().now().to_msg()

    def samples(self, msg: Samples) -> None:
        """Publish the message as one PointCloud2 table of n rows: film volts (float32, NaN when lost), ``t`` (s after the stamp), ``index``."""
        data, unix, dense = samples_table(msg)
        if len(self._fields) != msg.channels + 2:
            self._fields = [self.PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in field_names(msg.channels)]
        cloud = self.PointCloud2(height=1, width=msg.n, fields=self._fields, is_bigendian=False, point_step=4 * msg.channels + 12,
                                 row_step=(4 * msg.channels + 12) * msg.n, is_dense=dense)
        cloud.header.stamp = stamp(unix, self._now())
        cloud.header.frame_id = self.frame_id
        cloud.data = array.array("B", data)
        self.pub_samples.publish(cloud)

    def roughness(self, msg: Roughness) -> None:
        """Publish every roughness message as JSON on ``roughness/json``, and a final one's label ("" abstaining) on ``roughness``."""
        if msg.final:
            self.pub_label.publish(self.String(data=msg.label or ""))
        self.pub_json.publish(self.String(data=json.dumps(msg.to_map())))

    def withdrawn(self, msg: Slide) -> None:
        """Publish the slide message (event ``resumed``: that slide's final label is withdrawn) as JSON on ``roughness/json``."""
        self.pub_json.publish(self.String(data=json.dumps(msg.to_map())))

    def status(self, msg: Status) -> None:
        """Publish the status as JSON on ``status`` and as a DiagnosticStatus on ``/diagnostics``, stamped now."""
        self.pub_status.publish(self.String(data=json.dumps(msg.to_map())))
        st = self.DiagnosticStatus(level=bytes([LEVEL.get(msg.state, 0)]), name=f"tactiled/{self.sensor}", message=msg.state,
                                   hardware_id=self.sensor, values=[self.KeyValue(key=k, value=v) for k, v in status_values(msg)])
        arr = self.DiagnosticArray(status=[st])
        arr.header.stamp = self._now()
        self.pub_diag.publish(arr)

    def close(self) -> None:
        """Stop spinning (waiting up to 5 s each for the executor and its thread), destroy the node; shut rclpy down if this sink started it."""
        self.executor.shutdown(timeout_sec=5.0)
        self._spin.join(5.0)
        self.node.destroy_node()
        if self._owns_rclpy and self.rclpy.ok():
            self.rclpy.shutdown()
