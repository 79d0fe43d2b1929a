"""A surface none of whose slides the detector finds (a DC step, a still sensor) is refused by train (or left out with
--drop-rare) and by enrol: learnt at its true bounds it widened what the unknown-surface tests measure against, so that
an untaught surface was no longer called unknown (an audit: enrolled, 6 of 6 untaught slides labelled, 0 before)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tactiled.files.recording import Recording, save_recording
from tactiled.learn.model import load_model
from tactiled.sim.physics import SimParams
from tests.conftest import cli_here

FS = 20_000


def _dc_steps(path: Path, seed: int) -> None:
    """Six "slides" that are DC steps of 2000 counts on noise: ground truth the detector cannot see (it band-passes)."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((FS * 11, 2)) * 3.0
    starts = [int(FS * (0.8 + k * 1.8)) for k in range(6)]
    for a in starts:
        x[a:a + FS] += 2000.0
    save_recording(path, Recording(np.rint(x).astype(np.int16), float(FS), SimParams().volts_per_count, slide_start=np.array(starts),
                                   slide_stop=np.array(starts) + FS, surface=np.array(["Flat"] * 6)))


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], list[str]]:
    root = tmp_path_factory.mktemp("undetected")
    from tactiled.sim.simulate import write_dataset

    good = [str(p) for p in write_dataset(root / "sim", scene="robot", seed=3, files_per_surface=2, slides_per_file=3, surfaces="3")]
    flat = []
    for i in range(2):
        _dc_steps(root / f"flat_{i}.npz", i)
        flat.append(str(root / f"flat_{i}.npz"))
    return good, flat


def test_train_refuses_a_surface_the_detector_never_finds(data: tuple[list[str], list[str]], tmp_path: Path,
                                                          capfd: pytest.CaptureFixture[str]) -> None:
    good, flat = data
    out = tmp_path / "m.npz"
    res = cli_here(capfd, "train", "--method", "quick", "--folds", "2", "-o", str(out), *good, *flat)
    assert res.returncode == 2 and not out.exists()
    assert "the detector finds fewer than half of the slides of Flat (2 of 12)" in res.stderr and "--drop-rare" in res.stderr
    res = cli_here(capfd, "train", "--method", "quick", "--folds", "2", "--drop-rare", "-o", str(out), *good, *flat)
    assert res.returncode == 0 and "Flat" not in load_model(out).classes


def test_enrol_refuses_a_surface_the_detector_never_finds(data: tuple[list[str], list[str]], tmp_path: Path,
                                                          capfd: pytest.CaptureFixture[str]) -> None:
    good, flat = data
    base = tmp_path / "base.npz"
    assert cli_here(capfd, "train", "--method", "quick", "--folds", "2", "-o", str(base), *good).returncode == 0
    out = tmp_path / "enrolled.npz"
    res = cli_here(capfd, "enrol", str(base), *flat, "--label", "Flat", "-o", str(out))
    assert res.returncode == 2 and not out.exists()
    assert "the detector finds fewer than half of the slides of Flat (2 of 12)" in res.stderr and "nothing enrolled" in res.stderr
