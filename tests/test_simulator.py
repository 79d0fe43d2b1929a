"""The sensor model's physics and determinism, and the dataset CLI."""

from __future__ import annotations

import itertools
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactiled.files.recording import load_recording
from tactiled.sim.physics import SensorSimulator, SimParams, Surface, _self_affine_profile, default_surfaces, simulate_file
from tests.conftest import cli_here

QUIET = dict(noise_v=0.0, mains_v=0.0, drift_v=0.0, spike_rate_hz=0.0, stick_slip=False)


def test_rq_over_ra_of_gaussian_profiles() -> None:
    spec, _ = _self_affine_profile(2**21, 2e-6, default_surfaces()[4], np.random.default_rng(0))
    z = np.fft.irfft(spec, 2**21)
    assert abs(z.std() / np.abs(z).mean() - 1.2533) < 0.01


def _slide_rms(params: SimParams, surface: Surface, seed: int = 0) -> float:
    m = SensorSimulator(params, seed)
    m.add_rest(0.2)
    t = m.add_slide(surface, 1.0)
    v = m.read_volts(m.scheduled_end)
    return float(v[t.start + 4000:t.stop - 2000, 0].std())


def test_amplitude_rises_with_ra_at_fixed_speed_and_force() -> None:
    p = replace(SimParams(mode="robot", robot_force_sigma=0.0), **QUIET)  # type: ignore[arg-type]
    # one texture (lateral scale and Hurst exponent fixed), Ra swept over the default range
    rms = [_slide_rms(p, Surface(f"Ra{ra:.2f}", ra, 40.0, 0.7)) for ra in np.geomspace(0.44, 4.43, 8)]
    assert all(b > a for a, b in itertools.pairwise(rms))


def test_spectral_peak_moves_with_speed() -> None:
    peaks = []
    for speed in (0.03, 0.09):
        p = replace(SimParams(mode="robot", robot_speed_mps=speed, fn_hz=(5000.0, 5000.0), zeta=0.7), **QUIET)  # type: ignore[arg-type]
        m = SensorSimulator(p, 1)
        t = m.add_slide(default_surfaces()[10], 1.0)
        v = m.read_volts(m.scheduled_end)[t.start + 2000:t.stop - 2000, 0]
        spec = np.abs(np.fft.rfft(v * np.hanning(v.size))) ** 2
        f = np.fft.rfftfreq(v.size, 1 / p.fs)
        peaks.append(float(np.sum(f * spec) / np.sum(spec)))
    assert 2.0 < peaks[1] / peaks[0] < 4.0


def test_chunked_equals_one_shot_and_seeded() -> None:
    def run(chunks: list[int]) -> np.ndarray:
        m = SensorSimulator(SimParams(), 7)
        m.schedule_random(default_surfaces(), 60000)
        return np.concatenate([m.read(c) for c in chunks])

    one = run([60000])
    assert np.array_equal(one, run([1, 19, 20, 4000, 35960, 20000]))
    assert np.array_equal(one, run([60000]))
    assert not np.array_equal(one, SensorSimulator(SimParams(), 8).read(60000))


def test_finite_and_clipping_only_beyond_full_scale() -> None:
    p = replace(SimParams(), gain_v_per_mps=5000.0)
    m = SensorSimulator(p, 3)
    m.schedule_random(default_surfaces()[-3:], 80000)
    volts = m.read_volts(80000)
    assert np.all(np.isfinite(volts))
    from tactiled.sim.physics import adc

    counts = adc(volts, p.volts_per_count)
    clipped = (counts == 32767) | (counts == -32768)
    assert clipped.any()
    assert np.all(np.abs(volts[clipped]) >= 5.0 - p.volts_per_count)
    assert np.all(np.abs(volts[~clipped]) < 5.0)


def test_any_rate_and_channel_count() -> None:
    sim = simulate_file(replace(SimParams(), fs=2200.0, channels=1), default_surfaces()[3], 2, 0)
    assert sim.samples.shape[1] == 1 and len(sim.truth) == 2


def test_a_virtual_board_of_a_float_scene_sends_its_signal_in_counts() -> None:
    """``simulate serial --scene one-channel``: the scene's recordings are float volts (volts_per_count 1); its board sends
    int16 counts at the default ADC's scale, the same signal as the scene's files to within a count (not rounded to 1 V)."""
    from tactiled.sim.simulate import board_params, scene_for

    params = board_params("one-channel")
    assert (params.fs, params.channels, params.volts_per_count) == (2200.0, 1, SimParams.volts_per_count)
    board, files = SensorSimulator(params, 3), SensorSimulator(scene_for("one-channel")[1], 3)
    for model in (board, files):
        model.add_slide(default_surfaces()[5], 1.0)
    counts = board.read(board.scheduled_end).astype(np.float64)
    assert counts.std() > 100  # tens of mV at 153 uV a count (1 V a count rounded it to 0 and 1)
    expected = files.read_volts(files.scheduled_end)
    assert np.abs(counts * params.volts_per_count - expected).max() <= params.volts_per_count


def test_dataset_cli(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    # by main() in the test's process (cli_here): the same handler, lines and files; --jobs 2 still on worker processes
    res = cli_here(capfd, "simulate", "dataset", "--out", str(tmp_path), "--surfaces", "Ra0.44,Ra4.43", "--files-per-surface", "1",
                  "--slides-per-file", "2", "--scene", "robot")
    assert res.returncode == 0, res.stderr
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2
    rec = load_recording(files[0])
    assert rec.surface is not None and list(rec.surface) == ["Ra0.44", "Ra0.44"] and rec.meta["simulator"]["mode"] == "robot"
    assert np.all(rec.slide_stop > rec.slide_start)
    # worker processes write the same files, and say each surface done in order
    two = cli_here(capfd, "simulate", "dataset", "--out", str(tmp_path / "two"), "--surfaces", "Ra0.44,Ra4.43", "--files-per-surface", "1",
                  "--slides-per-file", "2", "--scene", "robot", "--jobs", "2")
    assert two.returncode == 0 and two.stderr.splitlines() == ["simulate: Ra0.44 (1/2)", "simulate: Ra4.43 (2/2)"], two.stderr
    assert [f.read_bytes() for f in files] == [(tmp_path / "two" / f.name).read_bytes() for f in files]
    bad = cli_here(capfd, "simulate", "dataset", "--out", str(tmp_path), "--surfaces", "Ra9")
    assert bad.returncode == 2 and "unknown surface 'Ra9'" in bad.stderr


# ---- another unit of the fingertip, new specimens of the same grades ------------------------------------------------


def test_other_units_differ_within_the_stated_tolerance() -> None:
    from tactiled.sim.physics import TOLERANCE, SimParams, other_unit

    base = SimParams()
    assert other_unit(base, 0) is base
    for unit in range(1, 20):
        p = other_unit(base, unit)
        assert p == other_unit(base, unit)  # deterministic in the unit number
        for k, (f, g) in enumerate(zip(p.fn_hz, p.film_gain, strict=True)):
            assert abs(f / base.fn_hz[k] - 1) <= TOLERANCE.resonance + 1e-12 and f <= 0.45 * base.fs
            assert abs(g / base.film_gain[k] - 1) <= TOLERANCE.film_gain + 1e-12
        assert abs(p.zeta / base.zeta - 1) <= TOLERANCE.damping + 1e-12 and abs(p.crosstalk / base.crosstalk - 1) <= TOLERANCE.crosstalk + 1e-12
        assert abs(p.tau_hp_s / base.tau_hp_s - 1) <= TOLERANCE.tau_hp + 1e-12
        assert TOLERANCE.noise[0] <= p.noise_v / base.noise_v <= TOLERANCE.noise[1]
    assert other_unit(base, 1).fn_hz != other_unit(base, 2).fn_hz
    with pytest.raises(ValueError, match="unit must be >= 0"):
        other_unit(base, -1)


def test_new_specimens_keep_the_grades() -> None:
    from tactiled.sim.physics import TOLERANCE, default_surfaces, grating_surfaces, new_specimens

    for make in (default_surfaces, grating_surfaces):
        nominal = make()
        assert new_specimens(nominal, 0) == nominal and make(0) == nominal
        for specimen in (1, 2, 7):
            other = make(specimen)
            assert other == new_specimens(nominal, specimen) == make(specimen)  # deterministic in the specimen number
            assert [s.name for s in other] == [s.name for s in nominal]
            assert [s.grade_ra_um for s in other] == [s.ra_um for s in nominal]  # the grade's nominal Ra: the label
            assert [s.period_um for s in other] == [s.period_um for s in nominal]
            for o, s in zip(other, nominal, strict=True):
                assert abs(o.ra_um / s.ra_um - 1) <= TOLERANCE.ra + 1e-12 and abs(o.corr_um / s.corr_um - 1) <= TOLERANCE.corr + 1e-12
                assert abs(o.hurst - s.hurst) <= TOLERANCE.hurst + 1e-12 and 0.5 <= o.hurst <= 0.95
            assert all(o.ra_um != s.ra_um and o.corr_um != s.corr_um for o, s in zip(other, nominal, strict=True))
        assert make(1) != make(2)
        assert new_specimens(make(1), 1)[0].grade_ra_um == nominal[0].ra_um  # a specimen of a specimen: still the grade's Ra


def test_specimen_zero_is_todays_surfaces_and_another_has_another_profile() -> None:
    from tactiled.sim.physics import default_surfaces, grating_surfaces, pick_surfaces

    first, last = default_surfaces()[0], default_surfaces()[-1]
    assert (first.name, first.ra_um, first.corr_um, first.hurst) == ("Ra0.44", 0.44, 39.515203688996024, 0.6421936392931707)
    assert (last.name, last.ra_um, last.corr_um, last.hurst) == ("Ra4.43", 4.43, 53.556153988663176, 0.6178969548598209)
    assert grating_surfaces()[0] == Surface("G0.10mm", 2.243832942507452, 53.029437444115175, 0.8, 100.0, 0.8)
    assert all(s.nominal_ra_um == 0.0 and s.grade_ra_um == s.ra_um for s in default_surfaces())
    # the same grade, another profile: the same random draws give another height profile with the same Ra label
    nominal, other = default_surfaces(0)[7], default_surfaces(1)[7]
    assert other.name == nominal.name and other.grade_ra_um == nominal.ra_um
    z0, z1 = (np.fft.irfft(_self_affine_profile(4096, 2e-6, s, np.random.default_rng(0))[0], 4096) for s in (nominal, other))
    assert not np.allclose(z0, z1)
    # a grade's specimen does not depend on which surfaces are picked
    assert pick_surfaces("Ra4.43", specimen=3) == [default_surfaces(3)[-1]]
    assert pick_surfaces(2, "grating", specimen=3) == [grating_surfaces(3)[0], grating_surfaces(3)[-1]]


def test_unit_zero_and_specimen_zero_write_todays_files(tmp_path: Path) -> None:
    from tactiled.sim.simulate import write_dataset

    kwargs: dict[str, Any] = {"scene": "robot", "surfaces": "Ra1.00", "files_per_surface": 1, "slides_per_file": 1, "seed": 5}
    today = load_recording(write_dataset(tmp_path / "a", **kwargs)[0])
    zero = load_recording(write_dataset(tmp_path / "b", unit=0, specimen=0, **kwargs)[0])
    other = load_recording(write_dataset(tmp_path / "c", unit=1, specimen=0, **kwargs)[0])
    assert np.array_equal(today.samples, zero.samples) and today.meta == zero.meta
    sim = simulate_file(replace(SimParams(), mode="robot"), default_surfaces()[5], 1, int(today.meta["seed"]))
    assert default_surfaces()[5].name == "Ra1.00" and np.array_equal(today.samples, sim.samples)
    assert not np.array_equal(today.samples, other.samples)


def test_simulate_dataset_of_another_unit_and_specimen(tmp_path: Path) -> None:
    from tactiled.cli.main import main
    from tactiled.files.recording import load_recording
    from tactiled.sim.physics import SimParams, other_unit

    assert main(["simulate", "dataset", "--out", str(tmp_path / "a"), "--scene", "robot", "--surfaces", "1", "--files-per-surface", "1",
                 "--slides-per-file", "1"]) == 0
    assert main(["simulate", "dataset", "--out", str(tmp_path / "b"), "--scene", "robot", "--surfaces", "1", "--files-per-surface", "1",
                 "--slides-per-file", "1", "--unit", "1", "--specimen", "1"]) == 0
    a, b = (load_recording(next((tmp_path / d).glob("*.npz"))) for d in "ab")
    assert (a.meta["unit"], a.meta["specimen"], b.meta["unit"], b.meta["specimen"]) == (0, 0, 1, 1)
    assert b.meta["simulator"]["fn_hz"] == list(other_unit(SimParams(), 1).fn_hz) and a.meta["simulator"]["fn_hz"] == [900.0, 1200.0]
    assert b.meta["surface"]["name"] == a.meta["surface"]["name"] and b.meta["surface"]["ra_um"] != a.meta["surface"]["ra_um"]
    assert b.meta["surface"]["nominal_ra_um"] == a.meta["surface"]["ra_um"]
    assert a.ra_um is not None and b.ra_um is not None and list(b.ra_um) == list(a.ra_um) == [0.44]  # the grade's label
    assert not np.array_equal(a.samples, b.samples)


def test_board_log_stays_bounded_when_nothing_reads_the_port(tmp_path: Path) -> None:
    """Nobody reads the pty: every frame overruns, yet the log gets one overrun line per second, and read_log gives every frame back."""
    import io
    import threading

    from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
    from tactiled.sim.virtualboard import VirtualBoard, read_log

    log = io.StringIO()
    board = VirtualBoard(SensorSimulator(SimParams(), seed=2), pick_surfaces(2), link=str(tmp_path / "tty"), speed=20.0, seed=2, log=log)
    import time

    board.open()
    began = time.monotonic()
    try:
        board.run(threading.Event(), seconds=20.0)  # 20 s of sensor time at 20x: about 1 s of wall time, 20 000 frames
    finally:
        board.close()
    wall_s = time.monotonic() - began
    (tmp_path / "board.jsonl").write_text(log.getvalue())
    lines = [line for line in log.getvalue().splitlines() if '"overrun"' in line]
    events = read_log(tmp_path / "board.jsonl")
    frames = [e["index"] for e in events if e["event"] == "overrun"]
    assert 1 <= len(lines) <= wall_s + 2  # one line per second of wall time, plus the last
    assert len(frames) > 15_000 and frames == sorted(set(frames)) and all(e["count"] == 20 for e in events if e["event"] == "overrun")


def test_rest_first_puts_that_long_at_rest_before_the_scenes_first_slide(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """simulate serial --rest-first S (the demo's board: the daemon is reading before the first slide): the board's log puts
    the first slide after S s plus one of the scene's rests (0.5-1.2 s), where without it the first slide comes after a rest."""
    from tactiled.sim.virtualboard import read_log

    firsts = {}
    for rest in ("0", "2.5"):
        log = tmp_path / f"board{rest}.jsonl"
        res = cli_here(capfd, "simulate", "serial", "--link", str(tmp_path / f"tty{rest}"), "--seconds", "6", "--speed", "40",
                       "--rest-first", rest, "--log", str(log))
        assert res.returncode == 0, res.stderr
        firsts[rest] = next(e["start"] for e in read_log(log) if e["event"] == "slide") / SimParams().fs
    assert 0.5 <= firsts["0"] <= 1.2 and 3.0 <= firsts["2.5"] <= 3.7, firsts
    refused = cli_here(capfd, "simulate", "serial", "--rest-first", "-1")
    assert refused.returncode == 2 and "--rest-first" in refused.stderr
