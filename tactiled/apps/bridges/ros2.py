"""ROS 2 bridge (``tactiled ros2``, extra ``tactiled[ros2]``: the ros-jazzy-* wheels, no colcon build).

Topics, for sensor ``<id>`` (standard message types only):

- ``/tactiled/<id>/roughness`` std_msgs/String: the final label ("" when abstaining);
- ``/tactiled/<id>/roughness/detail`` diagnostic_msgs/DiagnosticStatus: every roughness message
  (final and provisional), level OK with a label, WARN when abstaining (``message`` = the reason),
  every field as a key/value;
- ``/diagnostics`` diagnostic_msgs/DiagnosticArray: the status (OK connected/idle/sliding, ERROR
  disconnected, STALE stopping), every field as a key/value, stamped now;
- ``/tactiled/<id>/samples`` std_msgs/Float32MultiArray: each raw batch in volts, row-major
  (dim 0 "samples" = n, dim 1 "films" = channels; lost samples NaN). Float32MultiArray has no
  header, so each is preceded on ``/tactiled/<id>/samples/stamp`` by a std_msgs/Header whose
  stamp is the host time (unix) of the batch's first sample from the daemon's clock mapping and
  whose ``frame_id`` is that sample's index: pair them by order (both reliable, depth 100).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from tactiled_client import Roughness, Samples, Status, schema

from tactiled.apps.bridges import volts
from tactiled.extras import need

LEVEL = {schema.STATE_DISCONNECTED: 2, schema.STATE_STOPPING: 3}  # DiagnosticStatus ERROR, STALE; others OK


def stamp(unix: float | None, now: Any) -> Any:
    """builtin_interfaces/Time of a unix time (``now``, a Time, when None)."""
    if unix is None:
        return now
    time_cls = type(now)
    sec = int(unix // 1)
    return time_cls(sec=sec, nanosec=min(round((unix - sec) * 1e9), 999_999_999))


def key_values(kv_cls: Any, body: dict[str, Any]) -> list[Any]:
    return [kv_cls(key=k, value=str(v)) for k, v in body.items() if k not in ("data",)]


class Ros2Sink:
    """One rclpy node ``tactiled_<id>``; call :meth:`spin_once` or let the publishers run (they need no spinning)."""

    def __init__(self, sensor: str, node_name: str | None = None) -> None:
        self.rclpy: Any = need("rclpy", "ros2")
        std = need("std_msgs.msg", "ros2")
        diag = need("diagnostic_msgs.msg", "ros2")
        self.String, self.Float32MultiArray, self.MultiArrayDimension, self.Header = (std.String, std.Float32MultiArray,
                                                                                    std.MultiArrayDimension, std.Header)
        self.DiagnosticStatus, self.DiagnosticArray, self.KeyValue = diag.DiagnosticStatus, diag.DiagnosticArray, diag.KeyValue
        self._owns_rclpy = not self.rclpy.ok()
        if self._owns_rclpy:
            self.rclpy.init()
        self.node = self.rclpy.create_node(node_name or f"tactiled_{sensor}")
        base = f"/tactiled/{sensor}"
        self.sensor = sensor
        self.pub_label = self.node.create_publisher(self.String, f"{base}/roughness", 10)
        self.pub_detail = self.node.create_publisher(self.DiagnosticStatus, f"{base}/roughness/detail", 10)
        self.pub_diag = self.node.create_publisher(self.DiagnosticArray, "/diagnostics", 10)
        self.pub_samples = self.node.create_publisher(self.Float32MultiArray, f"{base}/samples", 100)
        self.pub_stamp = self.node.create_publisher(self.Header, f"{base}/samples/stamp", 100)

    def _now(self) -> Any:
        return self.node.get_clock().now().to_msg()

    def samples(self, msg: Samples) -> None:
        v, valid, _ = volts(msg)
        assert isinstance(v, np.ndarray) and isinstance(valid, np.ndarray)
        v[~valid] = np.nan
        self.pub_stamp.publish(self.Header(stamp=stamp(msg.index_unix, self._now()), frame_id=str(msg.index)))
        arr = self.Float32MultiArray()
        arr.layout.dim = [self.MultiArrayDimension(label="samples", size=msg.n, stride=msg.n * msg.channels),
                          self.MultiArrayDimension(label="films", size=msg.channels, stride=msg.channels)]
        arr.data = v.ravel().tolist()
        self.pub_samples.publish(arr)

    def roughness(self, msg: Roughness) -> None:
        if msg.final:
            self.pub_label.publish(self.String(data=msg.label or ""))
        status = self.DiagnosticStatus(level=bytes([0 if msg.label else 1]), name=f"tactiled/{self.sensor}/roughness",
                                       message=msg.label or msg.reason or "", hardware_id=self.sensor,
                                       values=key_values(self.KeyValue, msg.to_map()))
        self.pub_detail.publish(status)

    def status(self, msg: Status) -> None:
        level = LEVEL.get(msg.state, 0)
        st = self.DiagnosticStatus(level=bytes([level]), name=f"tactiled/{self.sensor}", message=msg.state, hardware_id=self.sensor,
                                   values=key_values(self.KeyValue, msg.to_map()))
        arr = self.DiagnosticArray(status=[st])
        arr.header.stamp = self._now()
        self.pub_diag.publish(arr)

    def close(self) -> None:
        self.node.destroy_node()
        if self._owns_rclpy and self.rclpy.ok():
            self.rclpy.shutdown()
