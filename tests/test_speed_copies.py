"""Speed-perturbed copies of training slides: what they are, that they only ever train, and how train and enrol take them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.analysis import window_settings
from tactiled.errors import ModelError
from tactiled.learn.dataset import collect_windows, find_slides, load_recordings, speed_ratios
from tactiled.learn.enrol import enrol
from tactiled.learn.model import load_model
from tactiled.learn.search import fit_pipeline, slide_scores
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three surfaces of the robot scene, two recordings of two slides each."""
    return write_dataset(tmp_path_factory.mktemp("speed"), scene="robot", seed=5, surfaces="3", files_per_surface=2, slides_per_file=2)


def test_speed_ratios() -> None:
    assert speed_ratios(0) == ()
    assert speed_ratios(5) == ((20, 21), (21, 20))  # 20 samples for every 21: played 5 % faster; and 5 % slower
    assert speed_ratios(2.5) == ((40, 41), (41, 40))
    assert speed_ratios(30) == ((10, 13), (13, 10))
    for bad in (-1.0, 30.5, float("nan"), float("inf"), 3.33):
        with pytest.raises(ValueError, match="per cent"):
            speed_ratios(bad)


def test_copies_are_extra_rows_of_their_slide_with_their_spectrum_moved(robot: list[Path]) -> None:
    recs = load_recordings(robot)
    config = Config()
    settings = window_settings(config, 2, recs[0][1].fs, 0.25, ["psd", "tex"])
    assert settings is not None
    found = find_slides(recs, config)
    plain = collect_windows(recs, config, settings, found=found)
    copied = collect_windows(recs, config, settings, found=found, speeds=speed_ratios(5))
    assert plain.copy is None and plain.originals().all()
    assert copied.copy is not None and set(copied.copy.tolist()) == {0, 1, 2}
    own = copied.originals()
    # the slides as recorded are the same rows, bit for bit; the slide table does not grow
    assert np.array_equal(copied.x[own], plain.x) and np.array_equal(copied.slide[own], plain.slide) and copied.slides == plain.slides
    for k in (1, 2):  # each copy holds about as many windows as its slide (5 % longer or shorter)
        assert abs(int(np.sum(copied.copy == k)) - len(plain.y)) <= len(plain.slides)
    # one whole-slide row per slide and per copy; the slides' rows are the plain ones
    means, plain_means = copied.averaged(), plain.averaged()
    assert means.copy is not None and len(means.y) == 3 * len(plain_means.y)
    assert np.array_equal(means.x[means.originals()], plain_means.x) and np.array_equal(means.slide[means.originals()], plain_means.slide)
    # played 5 % faster (copy 1), a slide's spectral centroid is higher; 5 % slower (copy 2), lower
    centroid = settings.names.index("film1.tex.centroid")
    per_copy = [np.log(means.x[means.copy == k, centroid]) for k in (0, 1, 2)]
    assert np.median(per_copy[1] - per_copy[0]) > 0.02 and np.median(per_copy[2] - per_copy[0]) < -0.02


def test_copies_train_but_are_never_scored(robot: list[Path]) -> None:
    recs = load_recordings(robot)
    config = Config()
    settings = window_settings(config, 2, recs[0][1].fs, 0.25, ["psd"])
    assert settings is not None
    ws = collect_windows(recs, config, settings, speeds=speed_ratios(10))
    assert ws.copy is not None
    classes = sorted(set(ws.y.tolist()))
    pipe, _ = fit_pipeline(ws.x, ws.y, ws.names, "linear", {"C": 10.0, "max_iter": 2000}, 0)
    slides = np.arange(len(ws.slides))
    spoiled = ws.x.copy()
    spoiled[ws.copy > 0] = 1e6  # a copy's rows, if a slide's score read them, would change it
    with_copies = slide_scores(ws, pipe, list(range(len(ws.names))), slides, classes)
    assert np.array_equal(with_copies, slide_scores(type(ws)(**{**ws.__dict__, "x": spoiled}), pipe, list(range(len(ws.names))), slides, classes))


def test_train_learns_from_copies_and_measures_the_slides_as_recorded(robot: list[Path], tmp_path: Path) -> None:
    config = Config()
    made = {speed: train(robot, config, method="quick", folds=2, speed=speed, progress=lambda m: None) for speed in (0.0, 5.0)}
    for speed, res in made.items():
        m = res.model
        assert m.summary.get("speed_copies", 0.0) == speed and ("speed_copies" in m.summary) == (speed > 0)
        assert res.oof is not None and res.oof[0].shape[0] == res.slides  # one out-of-fold score per slide as recorded
        assert m.novelty_x is not None and m.novelty_x.shape[0] == res.slides  # the unknown-surface test: the slides as recorded
    plain, copied = made[0.0].model, made[5.0].model
    assert plain.summary["windows"] == copied.summary["windows"]
    assert plain.refit is not None and copied.refit is not None
    assert len(copied.refit[1]) > 2.5 * len(plain.refit[1])  # the classifier learnt from the copies too
    path = tmp_path / "m.npz"
    copied.save(path)
    new = write_dataset(tmp_path / "new", scene="robot", seed=6, surfaces="3", files_per_surface=1, slides_per_file=2)[:2]  # not learnt
    done = enrol(path, new, config, label="NEW", min_slides=2)
    assert done.added == {"NEW": 4}  # slides counted as recorded
    assert done.model.refit is not None and list(done.model.refit[1]).count("NEW") > 2.5 * 4  # and learnt with their copies
    hostile = load_model(path)
    hostile.summary["speed_copies"] = "fast"
    hostile.fingerprint = ""
    hostile.save(tmp_path / "bad.npz")
    with pytest.raises(ModelError, match="speed_copies"):
        enrol(tmp_path / "bad.npz", new, config, label="NEW", min_slides=2)


def test_train_refuses_a_speed_it_cannot_resample_in_one_line(robot: list[Path], tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    res = cli_here(capfd, "train", *map(str, robot), "-o", str(tmp_path / "m.npz"), "--speed-copies", "3.33")
    one_line = "tactiled: error: --speed-copies: must be between 0 and 30 per cent, in steps of 0.1, got 3.33"
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [one_line], res.stderr
    res = cli_here(capfd, "train", *map(str, robot), "-o", str(tmp_path / "m.npz"), "--speed-copies", "40")
    assert res.returncode == 2 and "--speed-copies" in res.stderr and not (tmp_path / "m.npz").exists()


def test_copies_skip_a_slide_with_lost_samples_and_stay_finite_on_silent_and_clipped_slides(robot: list[Path]) -> None:
    from dataclasses import replace

    from tactiled.core.analysis import Analyser
    from tactiled.learn.dataset import LabelledSlide, speed_copies

    (_, rec), config = load_recordings(robot[:1])[0], Config()
    settings = window_settings(config, 2, rec.fs, 0.25, ["psd", "tex", "dwt"])
    assert settings is not None
    floats = Analyser(settings, rec.fs, 1.0, False)
    a, b, surface = rec.slides()[0]
    slide = LabelledSlide(0, a, b, surface, "truth")
    valid = rec.valid_mask()
    spans, rows, copies = speed_copies(floats, rec, valid, slide, speed_ratios(5))
    assert rows and set(copies) == {1, 2} and len(spans) == len(rows) == len(copies)
    lost = valid.copy()
    lost[a + 100:a + 120] = False  # samples lost inside the slide: nothing to resample, no copy
    assert speed_copies(floats, rec, lost, slide, speed_ratios(5)) == ([], [], [])
    full = np.iinfo(np.int16)
    rails = np.where(np.arange(rec.samples.shape[0]) % 2 == 0, full.max, full.min).astype(np.int16)
    for samples in (np.zeros_like(rec.samples), np.column_stack([rails, rails])):
        _, rows, _ = speed_copies(floats, replace(rec, samples=samples), valid, slide, speed_ratios(5))
        assert rows and all(np.isfinite(r).all() for r in rows)  # silent and rail-to-rail slides: finite features
