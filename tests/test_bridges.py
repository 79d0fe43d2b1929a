"""ROS 2 and LSL bridges, each inside a private network namespace (``unshare -rn``, loopback only).

The namespace side (tests/netns_bridges.py) binds a real PUB socket, runs the bridge on it,
publishes schema-built samples and roughness messages and receives them with a real LSL
inlet or ROS 2 subscriber; here we compare. No discovery traffic can leave the machine: the
namespace has no interface but ``lo`` (the script refuses to run otherwise).
"""

from __future__ import annotations

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


def expected(out: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(volts (n, 2), valid (n,), host index) of the batches sent after the consumer was connected."""
    volts = np.array(out["counts"], dtype=np.float64) * out["vpc"]
    valid = np.ones(len(volts), dtype=bool)
    for p, c in out["lost"]:
        valid[p:p + c] = False
    return volts, valid, out["first"] + np.arange(len(volts))


def test_lsl_outlets_carry_every_intact_sample_and_label_with_mapped_times(tmp_path: Path) -> None:
    pytest.importorskip("pylsl", reason="pylsl (tactiled[lsl]) does not import here")
    out = in_private_netns("lsl", tmp_path)
    got = out["got"]
    assert (got["channels"], got["nominal"], got["type"]) == (2, 20_000.0, "Tactile")
    assert got["labels"] == [["film1", "volts"], ["film2", "volts"]]
    volts, valid, index = expected(out)
    assert np.allclose(np.array(got["values"]), volts[valid], rtol=1e-6, atol=0)  # float32 of the volts, lost ones not pushed
    assert np.allclose(got["stamps"], out["base"] + index[valid] / out["fs"], rtol=0, atol=1e-6)  # the daemon's host times
    markers = [(json.loads(m), t) for m, t in got["markers"]]
    assert [(m["label"], m["final"], m["reason"]) for m, _ in markers] == [("Ra1.00", False, None), ("Ra1.18", True, None),
                                                                          (None, True, "low_confidence")]
    assert all(abs(t - (out["base"] + 2000 / out["fs"])) < 1e-6 for _, t in markers)  # stamped at the slide's stop


def test_ros2_bridge_publishes_labels_diagnostics_and_stamped_samples(tmp_path: Path) -> None:
    pytest.importorskip("rclpy", reason="the ROS 2 Jazzy wheels (tactiled[ros2]) do not import here")
    out = in_private_netns("ros2", tmp_path)
    got = out["got"]
    volts, valid, index = expected(out)
    n = out["n"]
    arrays = got["samples"][-(len(volts) // n):]
    stamps = got["stamp"][-(len(volts) // n):]
    assert [s[0] for s in stamps] == [str(i) for i in range(out["first"], out["first"] + len(volts), n)]
    assert np.allclose([s[1] for s in stamps], 1.7e9 + index[::n] / out["fs"], rtol=0, atol=2e-6)
    assert all(dims == [["samples", n, 2 * n], ["films", 2, 2]] for dims, _ in arrays)
    data = np.concatenate([np.array(d, dtype=np.float64).reshape(n, 2) for _, d in arrays])
    assert np.isnan(data[~valid]).all() and np.allclose(data[valid], volts[valid], rtol=1e-6, atol=0)
    assert got["label"] == ["Ra1.18", ""]  # final labels only; "" when abstaining
    assert [(lvl, msg, kv["final"]) for lvl, msg, kv in got["detail"]] == [(0, "Ra1.00", "False"), (0, "Ra1.18", "True"),
                                                                           (1, "low_confidence", "True")]
    name, message, values = got["diag"][0][0]
    assert (name, message, values["state"]) == ("tactiled/tip7", "idle", "idle")
