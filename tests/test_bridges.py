"""ROS 2 and LSL bridges, each inside a private network namespace (``unshare -rn``, loopback only).

The namespace side (tests/netns_bridges.py) binds a real PUB socket, runs the bridge on it,
publishes schema-built samples and roughness messages and receives them with a real LSL
inlet or ROS 2 subscriber; here we compare. No discovery traffic can leave the machine: the
namespace has no interface but ``lo`` (the script refuses to run otherwise).
"""

from __future__ import annotations

import importlib
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import REPO


def in_private_netns(kind: str, folder: Path) -> dict[str, Any]:
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"unshare -rn (a private network namespace) is not permitted here: {probe.stderr.strip()}")
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "42", "PYTHONPATH": str(REPO)}
    res = subprocess.run(["unshare", "-rn", "sh", "-c", f'ip link set lo up && exec "{sys.executable}" -m tests.netns_bridges {kind} "{folder}"'],
                         capture_output=True, text=True, timeout=180, cwd=REPO, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    out: dict[str, Any] = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["interfaces"] == ["lo"]
    return out


def expected(out: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(volts (n, 2), valid (n,), sensor index (n,), host monotonic time (n,)) of every row sent, in order."""
    counts = np.array(out["counts"], dtype=np.float64)
    volts, valid, index, mono = [], [], [], []
    for (first, n, lost, _), sent in zip(out["batches"], out["sent"], strict=True):
        ok = np.ones(n, dtype=bool)
        for p, c in lost:
            ok[p:p + c] = False
        volts.append(counts[first:first + n] * out["vpc"])
        valid.append(ok)
        index.append(first + np.arange(n))
        mono.append(sent["index_mono"] + np.arange(n) / sent["fs_clock"])
    return np.concatenate(volts), np.concatenate(valid), np.concatenate(index), np.concatenate(mono)


def lost_expected(out: dict[str, Any]) -> list[tuple[int, int]]:
    """Every lost range sent, those that run on into the next (across a message's end) as one."""
    ranges: list[tuple[int, int]] = []
    for first, _, lost, lost_before in out["batches"]:
        for start, count in ([(first - lost_before, lost_before)] if lost_before else []) + [(first + p, c) for p, c in lost]:
            if ranges and sum(ranges[-1]) == start:
                ranges[-1] = (ranges[-1][0], ranges[-1][1] + count)
            else:
                ranges.append((start, count))
    return ranges


def test_lsl_outlets_exist_from_start_up_carry_every_intact_sample_with_increasing_times_and_mark_every_loss(tmp_path: Path) -> None:
    importlib.import_module("pylsl")  # in the dev extras: a missing one fails
    out = in_private_netns("lsl", tmp_path)
    got = out["got"]
    assert got["resolved_before_samples"]  # both outlets resolved and opened before the first samples were sent
    assert (got["channels"], got["nominal"], got["type"]) == (2, 20_000.0, "Tactile")
    assert got["labels"] == [["film1", "volts", repr(out["vpc"])], ["film2", "volts", repr(out["vpc"])]]
    assert got["acquisition"] == {"manufacturer": "tactiled", "sensor_id": "tip7", "fs_firmware": "20000.0",
                                  "volts_per_count": repr(out["vpc"]), "model_fingerprint": "abc123"}
    volts, valid, _, mono = expected(out)
    assert np.allclose(np.array(got["values"]), volts[valid], rtol=1e-6, atol=0)  # float32 of the volts, lost ones not pushed
    stamps = np.array(got["stamps"])
    assert np.allclose(stamps, mono[valid], rtol=0, atol=1e-6)  # the daemon's host times
    assert np.diff(stamps).min() > 0  # increasing, the first read 31.8 ms late notwithstanding
    markers = [(json.loads(m), t) for m, t in got["markers"]]
    lost = [(m["index"], m["count"]) for m, _ in markers if m["event"] == "lost"]
    assert lost == lost_expected(out)
    labels = [m for m, _ in markers if m["event"] == "roughness"]
    assert [(m["label"], m["final"], m["reason"], m["model"]) for m in labels] == [("Ra1.00", False, None, "m"), ("Ra1.18", True, None, "m"),
                                                                                    (None, True, "low_confidence", "m")]
    assert all(m["novelty"] == 0.4 for m in labels)
    assert all(abs(t - out["stop_mono"]) < 1e-6 for m, t in markers if m["event"] == "roughness")  # stamped at the slide's stop


def test_ros2_bridge_takes_ros_args_and_publishes_self_stamped_samples_and_json(tmp_path: Path) -> None:
    importlib.import_module("rclpy")  # in the dev extras: a missing one fails
    out = in_private_netns("ros2", tmp_path)
    got = out["got"]
    assert out["sink"] == {"sensor": "tip7", "endpoint": f"ipc://{tmp_path}/pub", "frame_id": "tip_link"}  # -p parameters
    assert got["publishers_before_samples"] == [1]  # under the remapped namespace /robot1, before any samples
    volts, valid, index, _ = expected(out)
    by_index = {s["index"][0]: s for s in got["samples"]}
    assert len(by_index) >= len(out["batches"]) - 2  # sensor-data QoS is best effort: a message may be lost, none here in practice
    for (first, n, lost, _), sent in zip(out["batches"], out["sent"], strict=True):
        s = by_index.get(first)
        if s is None:
            continue
        assert s["frame"] == "tip_link" and s["width"] == n and s["dense"] is (not lost)
        assert s["fields"] == [["film1", 0, 7], ["film2", 4, 7], ["t", 8, 7], ["index", 12, 8]]
        assert abs(s["stamp"] - sent["index_unix"]) < 2e-6  # its own stamp: the daemon's unix time of its first row
        assert s["index"] == list(range(first, first + n))
        assert np.allclose(s["t"], np.arange(n) / sent["fs_clock"], rtol=0, atol=1e-7)
        rows = (index >= first) & (index < first + n)
        data = np.column_stack([s["film1"], s["film2"]])
        assert np.isnan(data[~valid[rows]]).all() and np.allclose(data[valid[rows]], volts[rows][valid[rows]], rtol=1e-6, atol=0)
    stamps = [by_index[k]["stamp"] for k in sorted(by_index)]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert got["label"] == ["Ra1.18", ""]  # final labels only; "" when abstaining
    assert [(j["label"], j["final"], j["reason"], j["top"]) for j in got["json"]] == [
        ("Ra1.00", False, None, [["Ra1.18", 0.8]]), ("Ra1.18", True, None, [["Ra1.18", 0.8]]), (None, True, "low_confidence", [["Ra1.18", 0.8]])]
    assert abs(got["json"][1]["stop_unix"] - out["stop_unix"]) < 2e-6
    assert all(j["novelty"] == 0.4 and j["grip_force_n"] == 1.5 for j in got["json"])  # a newer daemon's field kept
    assert got["status"][-1]["state"] == "idle" and got["status"][-1]["level"] == [0.01, 0.02]
    name, message, values = got["diag"][-1][0]
    assert (name, message, values["state"], values["level"], values["clock_index"]) == ("tactiled/tip7", "idle", "idle", "[0.01, 0.02]", "null")
