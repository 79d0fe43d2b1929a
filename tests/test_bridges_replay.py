"""A bridge on ``tactiled replay --publish --samples``: the raw samples, status and labels arrive as from a live daemon.

A real replay process publishes on an ipc socket; :func:`run_bridge` (no middleware: a sink that
records) subscribes, as ``tactiled lsl`` / ``tactiled ros2`` do.
"""

from __future__ import annotations

import itertools
import subprocess
import threading
from pathlib import Path

import numpy as np
from tactiled_client import Samples, Status, schema

from tactiled.apps.bridges import lost_ranges, run_bridge
from tactiled.files.recording import save_recording
from tests.conftest import REPO, BridgeSink, lossy_recording, standing_finals, tactiled_cmd


def test_a_bridge_on_a_replay_gets_every_sample_its_losses_status_and_labels(tmp_path: Path) -> None:
    first = 7_000_000
    rec = lossy_recording(first, slides=2, seed=5, lost=((1000, 37), (30_000, 2000)))
    samples = rec.samples
    save_recording(tmp_path / "r.npz", rec)
    endpoint = f"ipc://{tmp_path}/pub"
    sink, stop = BridgeSink(), threading.Event()
    bridge = threading.Thread(target=run_bridge, args=(endpoint, sink, stop, "fingertip0"), kwargs={"say": lambda line: None}, daemon=True)
    bridge.start()
    res = subprocess.run(tactiled_cmd("replay", str(tmp_path / "r.npz"), "--publish", endpoint, "--samples", "--speed", "20",
                                      "--wait-subscriber", "20"), capture_output=True, text=True, timeout=120, cwd=REPO)
    assert res.returncode == 0, res.stderr
    assert sink.stopping.wait(20), "no last (stopping) status"
    stop.set()
    bridge.join(10)
    raw = [m for m in sink.got if isinstance(m, Samples)]
    assert raw[0].index == first and all(b.index == a.index + a.n for a, b in itertools.pairwise(raw))  # every index once
    rows = np.concatenate([m.counts() for m in raw])
    valid = np.concatenate([m.valid() for m in raw])
    assert np.array_equal(valid, rec.valid_mask()) and np.array_equal(rows, samples)  # intact samples exact, lost rows zero and listed
    merged: list[list[int]] = []
    for a, c in sorted(r for m in raw for r in lost_ranges(m)):  # a range is split where messages split, as on a live daemon
        if merged and merged[-1][0] + merged[-1][1] == a:
            merged[-1][1] += c
        else:
            merged.append([a, c])
    assert merged == [[first + 1000, 37], [first + 30_000, 2000]]
    stamps = np.concatenate([m.index_mono + np.arange(m.n) / m.fs_clock for m in raw])  # type: ignore[operator]
    assert np.diff(stamps).min() > 0  # paced: host times that increase
    status = [m for m in sink.got if isinstance(m, Status)]
    assert len(status) >= 2 and status[-1].state == schema.STATE_STOPPING
    assert (status[-1].samples, status[-1].samples_lost, status[-1].index) == (len(samples) - 2037, 2037, first + len(samples))
    assert status[-1].slides == 2 and status[-1].model and len(status[-2].level) == 2 and status[-2].level[0] > 0
    labels = standing_finals(sink.got)
    assert len(labels) == 2 and all(first <= m.start < first + len(samples) for m in labels)


def _imported_by_replay(tmp_path: Path, options: list[str], names: list[str]) -> list[str]:
    """Which of the modules ``names`` a plain ``tactiled replay OPTIONS r.npz`` imports, run in a fresh interpreter (sorted)."""
    import json
    import sys

    save_recording(tmp_path / "r.npz", lossy_recording(0))
    code = ("import json, runpy, sys; names = json.loads(sys.argv[2]); sys.argv = ['tactiled', 'replay', *json.loads(sys.argv[3]), sys.argv[1]]\n"
            "try:\n    runpy.run_module('tactiled', run_name='__main__')\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "print(json.dumps(sorted(n for n in names if n in sys.modules)), file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "r.npz"), json.dumps(names), json.dumps(options)], capture_output=True,
                         text=True, timeout=120, check=True)
    found: list[str] = json.loads(out.stderr.strip().splitlines()[-1])
    return found


def test_a_replay_that_publishes_nothing_imports_neither_zeromq_nor_asyncio(tmp_path: Path) -> None:
    """Start-up: ZeroMQ, asyncio and the publishing side are imported only for ``replay --publish``."""
    assert _imported_by_replay(tmp_path, [], ["zmq", "asyncio", "tactiled.service.replay_feed"]) == []


def test_a_replay_with_the_default_config_imports_no_msgpack_toml_parser_or_statistics(tmp_path: Path) -> None:
    """Start-up: msgpack (packing a message), tomllib (a --config file) and statistics are not imported by a plain replay."""
    assert _imported_by_replay(tmp_path, ["--json"], ["msgpack", "tomllib", "statistics"]) == []
