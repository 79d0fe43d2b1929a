"""The samples table of ROS 2 messages (sensor_msgs/PointCloud2 used as a typed table), shared by ``tactiled ros2`` and
``tactiled export --profile ros2`` so the live topic and the bag hold the same rows.

One row per sample: ``film1`` … ``filmC`` (float32, volts, NaN when lost), ``t`` (float32, s after
``header.stamp``), ``index`` (float64, the sensor sample index, exact below 2**53); packed, little-endian.
"""

from __future__ import annotations

from typing import Any

import numpy as np

FLOAT32, FLOAT64 = 7, 8  # sensor_msgs/PointField datatypes


def table_dtype(channels: int) -> np.dtype[Any]:
    """The numpy dtype of one row: film1 … filmC (<f4), t (<f4), index (<f8); 4 C + 12 bytes."""
    return np.dtype([*((f"film{k + 1}", "<f4") for k in range(channels)), ("t", "<f4"), ("index", "<f8")])


def field_names(channels: int) -> list[tuple[str, int, int]]:
    """(name, byte offset, PointField datatype) of every column of the row, in order."""
    names = [f"film{k + 1}" for k in range(channels)] + ["t"]
    return [(n, 4 * k, FLOAT32) for k, n in enumerate(names)] + [("index", 4 * len(names), FLOAT64)]
