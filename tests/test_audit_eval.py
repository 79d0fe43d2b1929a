"""Audit of `tactiled evaluate`: (c) decimation keeps lost samples lost (and disconnections), and (g) says beside the
nested accuracy when it is optimistic, in report.md and report.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from tactiled.files.recording import Recording
from tactiled.learn.evaluate import LOST_REACH_TOL, decimate
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here


def _recording(lost: list[list[int]], *, zeros: bool = True, seed: int = 0) -> Recording:
    """20 kHz, 4 s, two channels of noise; one slide over 1-3 s; ``lost`` rows zero (or, ``zeros`` False, loud noise)."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((80_000, 2))
    for pos, count in lost:
        x[pos:pos + count] = 0.0 if zeros else 5.0 * rng.standard_normal((count, 2))
    return Recording(samples=x, fs=20_000.0, slide_start=np.array([20_000]), slide_stop=np.array([60_000]), label="P120",
                     lost=np.array(lost, dtype=np.int64).reshape(-1, 2))


@pytest.mark.parametrize("rate", [5000.0, 1000.0])
def test_decimate_keeps_lost_rows_lost_as_far_as_the_filter_carries_them(rate: float) -> None:
    lost = [[28_930, 6000]]
    zero_in, loud_in = _recording(lost), _recording(lost, zeros=False)
    zero, loud = decimate(zero_in, rate), decimate(loud_in, rate)
    q = round(20_000 / rate)
    valid = zero.valid_mask()
    assert len(zero.lost) and not valid.all()  # was: lost [] and every row valid
    assert not valid[28_930 // q:(28_930 + 6000) // q].any()  # at least the lost span at the new rate
    assert valid[:20_000 // q].all() and valid[45_000 // q:].all()  # the rest of the recording stays valid
    # outside what is listed lost, what was in the lost rows moves no output by LOST_REACH_TOL of their values (per stage)
    assert np.abs(zero.samples - loud.samples)[valid].max() < 2 * LOST_REACH_TOL * np.abs(loud_in.samples - zero_in.samples).max()
    assert np.abs(zero.samples - loud.samples)[~valid].max() > 1e-3  # and it does move the rows listed


def test_decimate_without_losses_is_unchanged_and_maps_disconnections() -> None:
    rec = _recording([])
    rec.disconnected = np.array([30_000, 30_001, 30_002, 80_000], dtype=np.int64)
    out = decimate(rec, 1000.0)
    expected = signal.decimate(signal.decimate(rec.volts(), 10, axis=0, zero_phase=True), 2, axis=0, zero_phase=True)
    assert np.array_equal(out.samples, expected)  # bit for bit what it was
    assert out.lost.shape == (0, 2) and out.valid_mask().all()
    assert out.disconnected.tolist() == [1500, 1501, 4000]  # the first output row after each, once


def test_evaluate_says_the_nested_accuracy_is_optimistic(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "d"
    write_dataset(data, scene="continuous,one-channel", surfaces="3", files_per_surface=2, seed=9)
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *sorted(str(p) for p in data.glob("*.npz")), "--report", str(report), "--quick", "--experiments", "g")
    assert res.returncode == 0, res.stderr
    assert "the nested estimate is optimistic" in res.stderr
    g = json.loads((report / "report.json").read_text())["default_method"]
    why = "one slide of a surface in a fold: no choice inside it"
    assert g["nested"]["inner_grouped_by"] == "none" and g["optimistic"] is True and g["optimistic_reason"] == why
    md = (report / "report.md").read_text()
    assert f"nested CV accuracy {100 * g['nested']['mean']:.1f} ± {100 * g['nested']['sd']:.1f} %, optimistic ({why})" in md
