"""What a label's numbers mean: calibrated confidence, novelty (unknown surfaces), and training that refuses what it cannot estimate.

The commands run by main() in the test's process (cli_here): the same handlers, lines and files, without a new interpreter
and worker pool for each."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tactiled.core.analysis import Analyser, AnalysisSettings
from tactiled.errors import ModelError
from tactiled.learn.model import Model, fit_pipeline, load_model, novelty_scores, softmax
from tactiled.learn.score import calibration_scores
from tactiled.learn.search import fit_calibration, fit_novelty, held_out_rejected
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here

NAMES = ("film1.psd.20-200Hz.power", "film1.psd.200-2000Hz.power", "film1.tex.centroid", "film1.tex.kurtosis")


def _oof(n: int, k: int, accuracy: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Scores (n, k) whose top class is right with probability ``accuracy``, and the true class indices."""
    rng = np.random.default_rng(seed)
    y = rng.integers(0, k, n)
    scores = rng.standard_normal((n, k))
    right = rng.random(n) < accuracy
    top = np.where(right, y, (y + 1) % k)
    scores[np.arange(n), top] += 3.0
    return scores, y


@pytest.mark.parametrize("n", [5, 60, 400])
def test_calibration_is_a_monotone_probability_map_never_certain(n: int) -> None:
    scores, y = _oof(n, 5, 0.7)
    temperature, knots, info = fit_calibration(scores, y)
    assert knots.shape[0] == 2 and np.all(np.isfinite(knots)) and np.all(np.diff(knots, axis=1) >= 0)
    assert knots[1].min() >= 1 / (n + 2) - 1e-12 and knots[1].max() <= 1 - 1 / (n + 2) + 1e-12
    assert math.isfinite(temperature) and temperature > 0
    assert info["method"] == ("constant" if n == 5 else "temperature")


def test_calibration_finds_the_temperature_of_overconfident_scores() -> None:
    """Labels drawn from softmax(z), scores 3 z: the fitted temperature undoes the factor, and the confidence averages to
    the accuracy."""
    rng = np.random.default_rng(0)
    z = 2.0 * rng.standard_normal((4000, 5))
    y = (softmax(z).cumsum(axis=1) > rng.random((4000, 1))).argmax(axis=1)
    temperature, knots, info = fit_calibration(3.0 * z, y)
    assert info["method"] == "temperature" and abs(temperature - 3.0) < 0.3
    conf = np.interp(softmax(3.0 * z, temperature).max(axis=1), knots[0], knots[1])
    assert abs(conf.mean() - info["accuracy"]) < 0.03


@pytest.mark.parametrize("case", ["all_right", "all_wrong", "no_scores", "one_class", "constant_scores", "huge_scores"])
def test_calibration_stays_finite_on_degenerate_slides(case: str) -> None:
    scores, y = _oof(50, 4, 0.6)
    if case == "all_right":
        y = np.argmax(scores, axis=1)
    elif case == "all_wrong":
        y = (np.argmax(scores, axis=1) + 1) % 4
    elif case == "no_scores":
        scores[:] = -np.inf
    elif case == "one_class":
        scores, y = scores[:, :1], np.zeros(50, dtype=np.intp)
    elif case == "constant_scores":
        scores[:] = 0.0
    elif case == "huge_scores":
        scores *= 1e300
    temperature, knots, _ = fit_calibration(scores, y)
    assert math.isfinite(temperature) and temperature > 0
    assert np.all(np.isfinite(knots)) and np.all((knots >= 0) & (knots <= 1)) and np.all(np.diff(knots, axis=1) >= 0)


def test_novelty_threshold_rejects_five_percent_of_known_and_flags_a_far_surface() -> None:
    rng = np.random.default_rng(1)
    centres = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [5.0, 5.0]])
    labels = np.repeat(np.arange(4), 40)
    files = np.repeat(np.arange(16), 10)  # four recordings per surface
    z = centres[labels] + 0.5 * rng.standard_normal((160, 2))
    threshold, info = fit_novelty(z, files, labels, 3)
    assert math.isfinite(threshold) and info["known_rejected"] <= 0.05 + 1e-9 and info["unseen_flagged"] > 0.9 and info["score"] == "ratio"
    far = novelty_scores(np.array([[20.0, 20.0], [0.1, 0.1], [2.5, 2.5]]), z, labels, 3) / threshold  # far from all; taught; between all four
    assert far[0] > 1.0 > far[1] and far[2] > 1.0


def test_a_shifted_sensor_keeps_the_surfaces_it_can_tell_apart() -> None:
    """The whole feature space moved by 3 within-surface spreads (another unit): known slides stay known, untaught ones are still flagged.

    A threshold at the edge of the training spread (the 95 % quantile of known scores) would reject most shifted slides."""
    rng = np.random.default_rng(2)
    centres = 10.0 * np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    labels = np.repeat(np.arange(4), 40)
    files = np.repeat(np.arange(16), 10)
    z = centres[labels] + 0.5 * rng.standard_normal((160, 2))
    shifted = z + np.array([1.5, 0.0])
    threshold, info = fit_novelty(z, files, labels, 3)
    scores = novelty_scores(shifted, z, labels, 3)
    assert np.mean(scores > threshold) < 0.05 and info["known_rejected"] <= 0.05
    edge = np.quantile([novelty_scores(z[i:i + 1], z[files != files[i]], labels[files != files[i]], 3)[0] for i in range(160)], 0.95)
    assert np.mean(scores > edge) > 0.5
    untaught = novelty_scores(np.array([[5.0, 5.0], [5.0, 0.0], [40.0, 40.0]]), z, labels, 3)  # between all four, between two, far from all
    assert np.all(untaught > threshold)


def test_the_threshold_never_rejects_more_than_asked_where_known_and_untaught_overlap() -> None:
    rng = np.random.default_rng(3)
    known, unseen = rng.uniform(0, 1, 500), rng.uniform(0, 1, 200)
    from tactiled.learn.search import novelty_threshold

    t = novelty_threshold(known, unseen, 0.05)
    assert np.mean(known > t) <= 0.05
    assert novelty_threshold(known, np.zeros(0), 0.05) == np.quantile(known, 0.95, method="higher")


def test_the_threshold_weighs_untaught_slides_by_their_expected_share() -> None:
    from tactiled.learn.search import novelty_threshold

    rng = np.random.default_rng(5)
    known = rng.standard_normal(400)
    for shift in (0.5, 1.0, 3.0, 6.0):  # untaught slides' scores from barely to far above the known ones'
        unseen = rng.standard_normal(200) + shift
        youden, rare = novelty_threshold(known, unseen, 0.05, 0.5), novelty_threshold(known, unseen, 0.05, 0.1)
        assert np.mean(known > youden) <= 0.05 and np.mean(known > rare) <= np.mean(known > youden)
        # at a share of 0.1 a rejected known slide costs nine times what a caught untaught one gains
        assert 0.1 * np.mean(unseen > rare) - 0.9 * np.mean(known > rare) >= 0.0
    # untaught scores within the known ones' range, twice as dense at the top: worth a threshold when both weigh alike
    # (Youden's J), not when one slide in ten is expected on an untaught surface
    flat, barely = np.linspace(0.0, 1.0, 400), np.linspace(0.5, 0.99, 200)
    assert math.isfinite(novelty_threshold(flat, barely, 0.05, 0.5)) and novelty_threshold(flat, barely, 0.05, 0.1) == math.inf
    far = rng.standard_normal(200) + 6.0
    t = novelty_threshold(known, far, 0.05, 0.1)
    assert np.mean(known > t) == 0.0 and np.mean(far > t) == 1.0  # apart: the same threshold whatever the share
    z = np.vstack([rng.standard_normal((12, 3)), rng.standard_normal((12, 3)) + 8.0])
    assert fit_novelty(z, np.arange(24) % 4, np.repeat([0, 1], 12), 3, untaught=0.3)[1]["untaught"] == 0.3


def test_train_refuses_a_share_of_untaught_slides_outside_0_1(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    res = cli_here(capfd, "train", str(tmp_path / "none.npz"), "-o", str(tmp_path / "m.npz"), "--untaught-share", "1.5")
    assert res.returncode == 2 and "--untaught-share" in res.stderr and len(res.stderr.strip().splitlines()) <= 2


@pytest.mark.parametrize("case", ["one_recording", "identical_slides", "one_slide"])
def test_novelty_stays_finite_when_cross_validation_cannot_judge(case: str) -> None:
    n = {"one_slide": 1}.get(case, 12)
    z = np.zeros((n, 3)) if case == "identical_slides" else np.random.default_rng(0).standard_normal((n, 3))
    files = np.zeros(n, dtype=int) if case in ("one_recording", "one_slide") else np.arange(n) % 4
    threshold, info = fit_novelty(z, files, np.arange(n) % 2, 3)
    assert threshold == math.inf and info["threshold"] is None  # no ratio gate: nothing to judge it by, or nothing it tells apart
    if case == "identical_slides":
        assert info["known_rejected"] == 0.0


def _model(tmp_path: Path) -> Model:
    rng = np.random.default_rng(0)
    y = np.repeat(["a", "b", "c"], 20)
    x = np.abs(rng.standard_normal((60, 4))) + np.repeat([1.0, 3.0, 9.0], 20)[:, None]
    pipe, refit = fit_pipeline(x, y, list(NAMES), "svm", {"C": 10.0})
    settings = AnalysisSettings(duration_s=0.25, names=NAMES, fusion="features")
    model = Model("test", "svm", {"C": 10.0}, ["a", "b", "c"], settings, 20000.0, 1, pipe, 1.0, 0, {}, "", refit,
                  np.array([[0.0, 0.5, 1.0], [0.2, 0.4, 0.9]]))
    model.novelty_x = model.standardise(x)
    model.novelty_threshold = 0.8
    model.save(tmp_path / "m.npz")
    return load_model(tmp_path / "m.npz")


def test_model_file_keeps_calibration_and_novelty(tmp_path: Path) -> None:
    model = _model(tmp_path)
    assert model.calibration is not None and model.novelty_x is not None and model.novelty_threshold == 0.8
    assert model.confidence(0.5) == pytest.approx(0.4) and model.confidence(0.75) == pytest.approx(0.65)


@pytest.mark.parametrize("signal", ["silent", "saturated", "constant", "spiky"])
def test_assessment_is_finite_on_extreme_windows(signal: str, tmp_path: Path) -> None:
    model = _model(tmp_path)
    n = round(0.25 * 20000)
    x = {"silent": np.zeros((n, 1)), "saturated": np.full((n, 1), 32767.0), "constant": np.full((n, 1), 3.0),
         "spiky": np.where(np.arange(n)[:, None] % 97 == 0, 1e6, 1e-3)}[signal]
    window = Analyser(model.settings, 20000.0, 1.0, integer=False).analyse(x)
    assert window.features is not None
    proba, confidence, novelty = model.assess(np.stack([window.features, window.features]))
    assert np.all(np.isfinite(proba)) and 0.0 <= confidence <= 1.0 and novelty is not None and math.isfinite(novelty)


@pytest.mark.parametrize(("change", "message"), [
    ({"calibration": np.array([[0.0, 1.0], [0.9, 0.1]])}, "calibration: knots must be nondecreasing"),
    ({"calibration": np.array([[0.0, np.nan], [0.0, 1.0]])}, "calibration: must be (2, m) finite floats"),
    ({"novelty_x": np.zeros((3, 7))}, "novelty_x: must be (n, 4) finite floats"),
])
def test_bad_trust_arrays_are_refused_in_one_line(change: dict, message: str, tmp_path: Path) -> None:
    from tactiled.files.recording import atomic_savez
    from tactiled.learn.model import _fingerprint

    model = _model(tmp_path)
    arrays = {**model._arrays(), **model._trust_arrays(), **change}
    header = model._header()
    header["fingerprint"] = _fingerprint(header, arrays)
    atomic_savez(tmp_path / "bad.npz", {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
    with pytest.raises(ModelError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        load_model(tmp_path / "bad.npz")
    assert "\n" not in str(info.value)


def _resaved(model: Model, path: Path, header_change: dict) -> Path:
    from tactiled.files.recording import atomic_savez
    from tactiled.learn.model import _fingerprint

    arrays = {**model._arrays(), **model._trust_arrays()}
    header = {**model._header(), **header_change}
    header["fingerprint"] = _fingerprint(header, arrays)
    atomic_savez(path, {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
    return path


def test_a_format_4_model_keeps_the_distance_it_was_fitted_with_and_a_bad_score_is_refused(tmp_path: Path) -> None:
    model = _model(tmp_path)
    assert model.novelty_score == "ratio"
    old = load_model(_resaved(model, tmp_path / "v4.npz", {"version": 4, "novelty": {"k": 3, "threshold": 0.8}}))
    assert old.novelty_score == "distance"
    with pytest.raises(ModelError, match=r"header\.novelty\.score: must be one of ratio, distance"):
        load_model(_resaved(model, tmp_path / "bad.npz", {"novelty": {"k": 3, "threshold": 0.8, "score": "cosine"}}))


def _isolated_surface() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slides (n, 2) of 20 surfaces on a grid 4 apart (10 slides in 2 recordings each) and one surface 40 beyond the grid (6 slides,
    2 recordings), with their surfaces and recordings."""
    rng = np.random.default_rng(5)
    grid = np.array([[x, y] for x in range(0, 20, 4) for y in range(0, 16, 4)], dtype=np.float64)
    centres = np.vstack([grid, [[60.0, 0.0]]])
    labels = np.concatenate([np.repeat(np.arange(20), 10), np.full(6, 20)])
    files = np.concatenate([np.repeat(np.arange(40), 5), [40, 40, 40, 41, 41, 41]])
    return centres[labels] + 0.5 * rng.standard_normal((len(labels), 2)), labels, files


def test_a_slide_far_from_every_taught_surface_is_flagged_even_where_the_ratio_is_small() -> None:
    """Near only an isolated surface, much nearer it than the next one: the ratio is small, the distance is not."""
    from tactiled.learn.model import novelty_parts, over_thresholds

    z, labels, files = _isolated_surface()
    threshold, info = fit_novelty(z, files, labels, 3, score="combined")
    far = info["distance_threshold"]
    assert info["score"] == "combined" and info["known_rejected"] <= 0.05 and far is not None and 0 < far < 10  # a grid step, not the isolation
    assert threshold == fit_novelty(z, files, labels, 3, score="ratio")[0]  # the ratio's threshold is the ratio score's
    slides = np.array([[60.0, 15.0], [60.3, 0.2], [8.2, 4.1], [2.0, 2.0], [-40.0, 6.0]])  # far; taught (isolated); taught; between; far
    ratio = novelty_scores(slides, z, labels, 3) / threshold
    both = over_thresholds(novelty_parts(slides, z, labels, 3, "combined"), threshold, far)
    assert ratio[0] < 1.0 < both[0]  # the case the ratio alone misses
    assert both[1] < 1.0 and both[2] < 1.0 and both[3] > 1.0 and both[4] > 1.0
    assert np.all(both >= ratio)


def _combined_model(tmp_path: Path, score: str = "combined") -> Model:
    """A model of three surfaces a, b, c (20 slides each, 5 per recording) with ``score``'s novelty, saved and loaded."""
    from tactiled.learn.search import fit_model_novelty

    rng = np.random.default_rng(0)
    y = np.repeat(["a", "b", "c"], 20)
    x = np.abs(rng.standard_normal((60, 4))) + np.repeat([1.0, 3.0, 9.0], 20)[:, None]
    model = _model(tmp_path)
    fit_model_novelty(model, x, y, np.arange(60) // 5, score)
    model.save(tmp_path / f"{score}.npz")
    return load_model(tmp_path / f"{score}.npz")


def test_a_combined_model_keeps_both_thresholds_and_flags_a_far_slide_not_a_known_one(tmp_path: Path) -> None:
    model = _combined_model(tmp_path)
    assert model.novelty_score == "combined" and math.isfinite(model.novelty_distance_threshold) and model.novelty_distance_threshold > 0
    assert model.summary["novelty"]["distance_threshold"] == model.novelty_distance_threshold
    known, far = np.full((2, 4), 3.5), np.full((2, 4), 300.0)
    known_nov, far_nov = model.assess(known)[2], model.assess(far)[2]
    assert known_nov is not None and far_nov is not None and known_nov < 1.0 < far_nov


def test_older_formats_keep_their_novelty_and_a_bad_distance_threshold_is_refused(tmp_path: Path) -> None:
    model = _combined_model(tmp_path)
    nov = {"k": 3, "threshold": model.novelty_threshold}
    v5 = load_model(_resaved(model, tmp_path / "v5.npz", {"version": 5, "novelty": {**nov, "score": "ratio", "distance_threshold": 1e-6}}))
    assert v5.novelty_score == "ratio" and v5.novelty_distance_threshold == math.inf  # format 5: no distance gate, whatever the header says
    far = np.full((2, 4), 300.0)
    assert v5.novelty(far) == pytest.approx(float(novelty_scores(v5.standardise(far.mean(axis=0, keepdims=True)), v5.novelty_x, v5.novelty_y,
                                                                         3)[0] / v5.novelty_threshold))
    v4 = load_model(_resaved(model, tmp_path / "v4.npz", {"version": 4, "novelty": nov}))
    assert v4.novelty_score == "distance"
    with pytest.raises(ModelError, match=r"header\.novelty\.score: must be one of ratio, distance$"):
        load_model(_resaved(model, tmp_path / "v5c.npz", {"version": 5, "novelty": {**nov, "score": "combined"}}))
    with pytest.raises(ModelError, match=r"header\.novelty\.distance_threshold: must be a number > 0 or null"):
        load_model(_resaved(model, tmp_path / "bad.npz", {"novelty": {**nov, "score": "combined", "distance_threshold": -1.0}}))


def test_combined_novelty_stays_finite_on_one_surface_and_on_extreme_windows(tmp_path: Path) -> None:
    from tactiled.learn.search import fit_model_novelty

    z = np.random.default_rng(1).standard_normal((12, 3))
    threshold, info = fit_novelty(z, np.arange(12) % 4, np.zeros(12, dtype=int), 3, score="combined")
    assert math.isfinite(threshold) and info["distance_threshold"] is None  # one surface: the distance, no second gate
    model = _combined_model(tmp_path)
    n = round(0.25 * 20000)
    for x in (np.zeros((n, 1)), np.full((n, 1), 32767.0), np.full((n, 1), 3.0)):
        window = Analyser(model.settings, 20000.0, 1.0, integer=False).analyse(x)
        assert window.features is not None
        novelty = model.assess(np.stack([window.features, window.features]))[2]
        assert novelty is not None and math.isfinite(novelty)
    one = _model(tmp_path)
    x = one.unstandardise(one.novelty_x if one.novelty_x is not None else np.zeros((0, 4)))
    fit_model_novelty(one, one.standardise(x), np.full(len(x), "a"), np.arange(len(x)) // 5, "combined")
    one.save(tmp_path / "one.npz")
    loaded = load_model(tmp_path / "one.npz")
    assert loaded.novelty_distance_threshold == math.inf
    for features in (np.full((2, 4), 3.5), np.full((2, 4), 1e30), np.zeros((2, 4))):
        novelty = loaded.assess(features)[2]
        assert novelty is not None and math.isfinite(novelty)


def test_provisional_confidence_comes_from_the_early_map_and_survives_the_file(tmp_path: Path) -> None:
    model = _model(tmp_path)
    x = np.abs(np.random.default_rng(5).standard_normal((2, 4))) + 3.0
    assert model.early_calibration is None and model.assess(x, final=False)[1] == model.assess(x)[1]  # no early map: the slide's
    model.early_calibration = (0.0, 0.0, math.log(0.3 / 0.7))
    model.save(tmp_path / "e.npz")
    loaded = load_model(tmp_path / "e.npz")
    assert loaded.early_calibration == pytest.approx((0.0, 0.0, math.log(0.3 / 0.7)))
    assert loaded.assess(x, final=False)[1] == pytest.approx(0.3) and loaded.assess(x)[1] == model.assess(x)[1]
    with pytest.raises(ModelError, match=r"header\.early_calibration: must be three finite numbers or null"):
        load_model(_resaved(model, tmp_path / "bad.npz", {"early_calibration": [1.0, "x", 0.0]}))


@pytest.mark.parametrize("p_top", [0.0, 1.0, 1e-300, float("nan"), 0.5])
@pytest.mark.parametrize("windows", [0, 1, 10**9])
def test_early_probability_is_a_probability_short_of_certain(p_top: float, windows: int) -> None:
    from tactiled.learn.model import early_probability

    for coef in ((1.0, 0.5, 0.0), (1e300, 1e300, -1e300), (0.0, 0.0, 0.0)):
        assert 0.01 <= early_probability(coef, p_top, windows) <= 0.99
    assert early_probability((2.0, 0.0, 0.0), 0.9, 1) > early_probability((2.0, 0.0, 0.0), 0.6, 1)


@pytest.mark.parametrize("n", [40, 60, 1000])
def test_a_provisional_label_is_never_surer_than_the_final_map_allows(n: int, tmp_path: Path) -> None:
    """The early map was clamped to a fixed [0.01, 0.99] whatever the training slides: a model trained on 40 slides, all
    right (its final map the constant 41/42 = 0.9762), gave 0.99 from one window. Now the final map's range bounds it (at
    most 0.99), through the file too."""
    model = _model(tmp_path)
    x = np.abs(np.random.default_rng(5).standard_normal((2, 4))) + 3.0
    scores, y = _oof(n, 4, 1.0 if n == 40 else 0.8)
    model.temperature, model.calibration, _ = fit_calibration(scores, y)
    top = float(np.max(model.calibration[1]))
    assert top == pytest.approx(41 / 42 if n == 40 else 1 - 1 / (n + 2))
    model.early_calibration = (1.0, 0.0, 50.0)  # every provisional label as sure as the map lets it be
    model.save(tmp_path / "m.npz")
    for m in (model, load_model(tmp_path / "m.npz")):
        assert m.assess(x, final=False)[1] == pytest.approx(min(top, 0.99)) and m.assess(x)[1] <= top
        m.early_calibration = (1.0, 0.0, -50.0)
        assert m.assess(x, final=False)[1] == pytest.approx(max(1 / (n + 2), 0.01) if n != 40 else 1 - 41 / 42)


def test_the_spectrum_tests_known_rejected_is_of_each_recording_left_out() -> None:
    """fit_novelty counted the slides its own scales were fitted on (each surface's 95 % quantile of its own slides'
    distances: with 12 slides, their largest): 0 % of known slides called unknown, whatever a new recording did. Now each
    recording's slides are counted against the threshold and scales fitted on the others, as fitting on them alone gives."""
    from tactiled.learn.model import surface_distances

    rng = np.random.default_rng(0)
    labels, files = np.repeat(np.array(list("abcd")), 12), np.repeat(np.arange(12), 4)
    z = rng.standard_normal((48, 6)) + np.searchsorted(np.unique(labels), labels)[:, None] * 0.8 + rng.standard_normal((12, 6))[files]
    _, info = fit_novelty(z, files, labels, 3, score="spectrum")
    rejected = 0
    for r in range(12):
        rest = files != r
        _, fitted = fit_novelty(z[rest], files[rest], labels[rest], 3, score="spectrum")
        near = surface_distances(z[~rest], z[rest], labels[rest], 3) / np.array(fitted["surface_scale"])
        rejected += int(np.sum(near.min(axis=1) / fitted["distance_threshold"] > 1.0))
    assert info["known_rejected_by"] == "recording left out" and info["known_rejected"] == pytest.approx(rejected / 48) and rejected > 0
    assert held_out_rejected(z, files, labels, 3, np.full((48, 4), 1e-12)) == 0.0  # every slide at no distance: none beyond


def test_calibration_scores_of_a_perfect_and_an_overconfident_model() -> None:
    right = np.array([True] * 8 + [False] * 2)
    assert calibration_scores(np.full(10, 0.8), right)["ece"] == pytest.approx(0.0)
    over = calibration_scores(np.full(10, 1.0), right)
    assert over["ece"] == pytest.approx(0.2) and over["brier"] == pytest.approx(0.2) and over["reliability"] == [[0.9, 10, 1.0, 0.8]]
    assert calibration_scores(np.array([]), np.array([], dtype=bool))["ece"] is None


def test_the_ece_a_calibrated_model_would_show_is_large_on_few_mid_range_slides_and_nil_when_sure() -> None:
    """90 slides at confidence 0.5: the ECE is |accuracy - 0.5| with accuracy ~ Binomial(90, 0.5) / 90 (sd 0.053), so its
    median is 0.6745 sd = 0.036 and its 95th percentile 1.96 sd = 0.103; a model always right at confidence 1 shows 0."""
    median, q95 = calibration_scores(np.full(90, 0.5), np.arange(90) % 2 == 0)["ece_calibrated"]
    assert 0.025 <= median <= 0.05 and 0.085 <= q95 <= 0.12
    assert calibration_scores(np.ones(90), np.ones(90, dtype=bool))["ece_calibrated"] == [0.0, 0.0]
    assert calibration_scores(np.full(90, 0.5), np.ones(90, dtype=bool))["ece_calibrated"] == [median, q95]  # seeded: the same draws
    assert calibration_scores(np.array([]), np.array([], dtype=bool))["ece_calibrated"] is None


def test_train_and_evaluate_refuse_a_surface_with_one_recording_train_allows_it_by_slide(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    write_dataset(data, scene="robot", surfaces="3", files_per_surface=1, slides_per_file=4, fs=2200.0, channels=1)
    files = sorted(str(p) for p in data.glob("*.npz"))
    res = cli_here(capfd, "train", *files, "-o", str(tmp_path / "m.npz"), "--folds", "2", "--method", "quick")
    assert res.returncode == 2 and not (tmp_path / "m.npz").exists()
    error = res.stderr.strip().splitlines()[-1]
    assert "single recording" in error and "Ra0.44" in error and "--group-by slide" in error
    res = cli_here(capfd, "train", *files, "-o", str(tmp_path / "m.npz"), "--folds", "2", "--method", "quick", "--group-by", "slide")
    assert res.returncode == 0, res.stderr
    assert "optimistic" in res.stderr and "confidence: calibrated" in res.stdout and load_model(tmp_path / "m.npz").novelty_x is not None
    res = cli_here(capfd, "evaluate", *files, "--report", str(tmp_path / "report"), "--quick", "--experiments", "a")  # it printed 0.0 % for all
    assert res.returncode == 2 and not (tmp_path / "report").exists()
    assert "single recording" in res.stderr.strip().splitlines()[-1] and "--group-by" not in res.stderr


def test_train_and_evaluate_refuse_a_recording_given_twice(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """The same samples under two names (a copy, or one file matched by two globs): grouped folds would test a recording on
    its copy (cross-validation then promised 100 % on the hand scene), so train and evaluate stop with one line naming both."""
    data = tmp_path / "data"
    write_dataset(data, scene="robot", surfaces="2", files_per_surface=1, slides_per_file=2, fs=2200.0, channels=1)
    files = sorted(data.glob("*.npz"))
    copy = data / "copy.npz"
    copy.write_bytes(files[0].read_bytes())
    argv = [*map(str, files), str(copy)]
    for command in (["train", *argv, "-o", str(tmp_path / "m.npz")], ["evaluate", *argv, "--report", str(tmp_path / "r")]):
        res = cli_here(capfd, *command)
        line = res.stderr.strip().splitlines()[-1]
        assert res.returncode == 2 and "hold the same samples" in line and files[0].name in line and "copy.npz" in line, res.stderr
    assert not (tmp_path / "m.npz").exists() and not (tmp_path / "r").exists()


def test_train_on_unlabelled_recordings_says_so_at_once(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    from tactiled.files.recording import Recording, save_recording

    rng = np.random.default_rng(0)
    for i in range(2):
        save_recording(tmp_path / f"u{i}.npz", Recording(samples=(rng.standard_normal((22000, 1)) * 100).astype(np.int16), fs=2200.0))
    res = cli_here(capfd, "train", str(tmp_path / "u0.npz"), str(tmp_path / "u1.npz"), "-o", str(tmp_path / "m.npz"))
    assert res.returncode == 2 and "no labelled slides" in res.stderr.strip().splitlines()[-1]


def test_a_surface_unlike_every_training_slide_gets_no_label_and_is_counted() -> None:
    """Every final result of a model that finds everything novel abstains with unknown_surface; the pipeline counts them for status."""
    from tactiled.config import Config
    from tactiled.core.events import SlideResult
    from tactiled.core.pipeline import Pipeline
    from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file

    model = load_model()
    model.novelty_threshold = 1e-9  # nothing is near enough to a training slide
    params = SimParams(mode="robot")
    sim = simulate_file(params, pick_surfaces("Ra1.00")[0], 2, 5)
    pipe = Pipeline(Config(), params.fs, params.channels, params.volts_per_count, model=model)
    events = pipe.feed(0, sim.samples) + pipe.finish()
    finals = [e for e in events if isinstance(e, SlideResult) and e.final]
    assert len(finals) == 2 and all(r.label is None and r.reason == "unknown_surface" and r.novelty is not None and r.novelty > 1 for r in finals)
    assert all(r.top and r.confidence is not None for r in finals)  # what it resembles most is still said
    assert pipe.unknown == 2 and pipe.labels == 0
    assert not [e for e in events if isinstance(e, SlideResult) and not e.final]  # no provisional label for a novel slide


def test_shadow_stats_pair_overlapping_slides_and_count_agreement_confidence_and_unknowns() -> None:
    from tactiled.core.events import SlideResult
    from tactiled.core.shadow import PENDING_MAX, ShadowStats

    def result(start: int, label: str | None, confidence: float | None = None, reason: str | None = None, final: bool = True) -> SlideResult:
        return SlideResult(0, start, start + 100, (start, start + 100), label, reason, confidence, [], {}, final=final)

    stats = ShadowStats(model="cafe")
    assert stats.summary() == {"model": "cafe", "slides": 0, "agreement": None, "confidence": None, "unknown_rate": None}
    stats.add_live(result(0, "Ra1"))
    stats.add_shadow(result(0, "Ra1", 0.8))  # agrees
    stats.add_shadow(result(500, None, reason="unknown_surface"))  # the candidate first, then the live one: disagrees
    stats.add_live(result(500, "Ra2"))
    stats.add_shadow(result(900, "Ra2", 0.4, final=False))  # provisional: not compared
    stats.add_live(result(1000, None, reason="samples_lost"))
    stats.add_shadow(result(1010, None, reason="samples_lost"))  # both null: agree (a shadow's slide may start a hop apart)
    assert stats.summary() == {"model": "cafe", "slides": 3, "agreement": 2 / 3, "confidence": 0.8, "unknown_rate": 1 / 3}
    for k in range(3 * PENDING_MAX):  # results the other model never matches stay bounded
        stats.add_live(result(10_000 + k, "Ra1"))
    assert len(stats._live) <= PENDING_MAX


def test_shadow_stats_uncount_a_withdrawn_final_label() -> None:
    from tactiled.core.events import SlideResult
    from tactiled.core.shadow import ShadowStats

    def result(stop: int, label: str | None, confidence: float | None = None) -> SlideResult:
        return SlideResult(0, 0, stop, (0, stop), label, None, confidence, [], {})

    stats = ShadowStats(model="cafe")
    stats.add_live(result(100, "Ra1"))
    stats.add_shadow(result(100, "Ra2", 0.6))  # paired at the early end: disagree
    stats.withdraw(shadow=False)  # the slide went on: both early labels are withdrawn, in either order
    stats.withdraw(shadow=True)
    assert stats.summary() == {"model": "cafe", "slides": 0, "agreement": None, "confidence": None, "unknown_rate": None}
    stats.add_shadow(result(900, "Ra1", 0.9))  # the real end: the candidate first this time
    stats.add_live(result(900, "Ra1"))
    assert stats.summary() == {"model": "cafe", "slides": 1, "agreement": 1.0, "confidence": 0.9, "unknown_rate": 0.0}
    stats.add_live(result(1900, "Ra3"))  # one model withdraws, the other's result waits for the new pair
    stats.add_shadow(result(1900, "Ra3", 0.5))
    stats.withdraw(shadow=True)
    stats.add_shadow(result(2500, "Ra2", 0.7))
    assert (stats.slides, stats.agreed, stats.finals, round(stats.confidence_sum, 6)) == (2, 1, 2, 1.6)


def test_the_nested_estimates_interval_resamples_recordings_not_slides() -> None:
    """recording_interval: a percentile bootstrap over whole recordings; wider when slides of a recording agree (they carry
    less), the accuracy inside it, None with fewer than 3 recordings, the rule of three when every slide is right or wrong."""
    from tactiled.learn.score import recording_interval

    rng = np.random.default_rng(2)
    groups = np.repeat(np.arange(40), 5)
    independent = rng.random(200) < 0.6
    clustered = np.repeat(rng.random(40) < 0.6, 5)  # a recording all right or all wrong
    loose, tight = recording_interval(clustered, groups), recording_interval(independent, groups)
    assert loose is not None and tight is not None
    assert loose[0] <= clustered.mean() <= loose[1] and tight[0] <= independent.mean() <= tight[1]
    assert loose[1] - loose[0] > 1.5 * (tight[1] - tight[0])
    assert recording_interval(independent[:10], groups[:10]) is None  # two recordings
    assert recording_interval(np.ones(200, dtype=bool), groups) == [1.0 - 3 / 40, 1.0]  # the rule of three over 40 recordings
    assert recording_interval(np.zeros(200, dtype=bool), groups) == [0.0, 3 / 40]


def test_the_far_test_is_combined_without_its_ratio_and_flags_only_a_slide_far_from_every_surface(tmp_path: Path) -> None:
    """train --novelty far: the ratio's threshold is inf, the distance threshold the combined score's; the file says combined
    (no format change) and the summary far; a slide between two surfaces is not flagged, a far one is; finite on one surface."""
    from tactiled.learn.model import novelty_parts, over_thresholds

    z, labels, files = _isolated_surface()
    threshold, info = fit_novelty(z, files, labels, 3, score="far")
    combined = fit_novelty(z, files, labels, 3, score="combined")[1]
    assert threshold == math.inf and info["score"] == "far" and info["threshold"] is None
    assert info["distance_threshold"] == combined["distance_threshold"] and info["known_rejected"] <= 0.05
    slides = np.array([[60.0, 15.0], [8.2, 4.1], [2.0, 2.0], [-40.0, 6.0]])  # far; taught; between two; far
    nov = over_thresholds(novelty_parts(slides, z, labels, 3, "combined"), threshold, info["distance_threshold"])
    assert nov[0] > 1.0 and nov[1] < 1.0 and nov[2] < 1.0 and nov[3] > 1.0  # the slide between two surfaces keeps its label
    loaded = _combined_model(tmp_path, "far")
    assert loaded.novelty_score == "combined" and loaded.summary["novelty"]["score"] == "far" and loaded.novelty_threshold == math.inf
    assert math.isfinite(loaded.novelty_distance_threshold)
    known, far = loaded.assess(np.full((2, 4), 3.5))[2], loaded.assess(np.full((2, 4), 300.0))[2]
    assert known is not None and far is not None and known < 1.0 < far
    threshold, info = fit_novelty(z[:12], np.arange(12) % 4, np.zeros(12, dtype=int), 3, score="far")  # one surface: no test
    assert threshold == math.inf and info["distance_threshold"] is None


def test_with_two_surfaces_the_ratio_claims_no_untaught_surface_it_cannot_measure() -> None:
    """Two surfaces: leaving one out leaves one, with no second-nearest surface, so no ratio; its column held a plain
    distance, the ratio threshold landed between ratios (at most 1) and distances (6.3), and train said 100 % of untaught
    slides were flagged where the model could flag none (an outside review). Now the ratio claims nothing: ``ratio`` says
    no figure, ``combined`` counts only its distance test."""
    from tactiled.learn.search import fit_novelty

    rng = np.random.default_rng(0)
    z = np.concatenate([rng.normal(0.0, 1.0, (20, 4)), rng.normal(6.0, 1.0, (20, 4))])
    labels = np.array(["A"] * 20 + ["B"] * 20)
    files = np.array([0] * 10 + [1] * 10 + [2] * 10 + [3] * 10)
    threshold, info = fit_novelty(z, files, labels, 3, score="ratio")
    assert info["unseen_flagged"] is None and (math.isinf(threshold) or threshold <= 1.0), info
    _, info = fit_novelty(z, files, labels, 3, score="combined")
    assert info["unseen_flagged"] is not None and info["distance_threshold"] is not None
