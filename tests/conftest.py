"""Shared test helpers: waiting on events with a timeout, running the CLI as a process."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:
    from tactiled.files.recording import Recording

REPO = Path(__file__).resolve().parents[1]


def wait_for(predicate: Callable[[], object], timeout: float = 20.0, what: str = "condition") -> object:
    """Call ``predicate`` until it returns something truthy; fail after ``timeout`` seconds.

    ``predicate`` must itself wait for the next event (e.g. a subscriber's ``receive`` with a
    timeout), so this loop never sleeps or spins.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def tactiled_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "tactiled", *args]


def run_cli(*args: str, timeout: float = 120.0, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(tactiled_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=REPO, **kw)  # type: ignore[call-overload, no-any-return]


@pytest.fixture
def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONUNBUFFERED"] = "1"
    return e


def lossy_recording(first_index: int, meta: dict[str, object] | None = None, *, slides: int = 3, seed: int = 7,
                    lost: tuple[tuple[int, int], ...] = ((1000, 37), (50_000, 20))) -> Recording:
    """A simulated recording of Ra2.29 (``slides`` slides, ``seed``) with its ground truth, ``first_index`` and the
    ``lost`` ranges (position, count) zeroed and listed."""
    from tactiled.files.recording import Recording
    from tactiled.sim.sensor_model import SimParams, pick_surfaces, simulate_file

    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra2.29")[0], slides, seed)
    ranges = np.array(lost, dtype=np.int64).reshape(-1, 2)
    samples = sim.samples.copy()
    for p, c in ranges:
        samples[p:p + c] = 0
    return Recording(samples, params.fs, params.volts_per_count, slide_start=np.array([t.start for t in sim.truth]),
                     slide_stop=np.array([t.stop for t in sim.truth]), surface=np.array([t.surface.name for t in sim.truth]),
                     first_index=first_index, lost=ranges, meta=meta or {})


class BridgeSink:
    """What a bridge hands to its outlets, kept: every samples, roughness and status message in order (``got``);
    ``stopping`` is set at the daemon's last status, ``closed`` when the bridge closes its outlets."""

    def __init__(self) -> None:
        self.got: list[object] = []
        self.stopping = threading.Event()
        self.closed = threading.Event()

    def samples(self, msg: object) -> None:
        self.got.append(msg)

    def roughness(self, msg: object) -> None:
        self.got.append(msg)

    def status(self, msg: object) -> None:
        self.got.append(msg)
        if getattr(msg, "state", None) == "stopping":  # schema.STATE_STOPPING
            self.stopping.set()

    def close(self) -> None:
        self.closed.set()
