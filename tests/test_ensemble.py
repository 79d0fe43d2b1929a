"""An ensemble model (format 7): the chosen candidate and the plain spectral one over one analysis, their probabilities multiplied."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.analysis import Analyser
from tactiled.errors import ModelError
from tactiled.files.recording import atomic_savez
from tactiled.learn.enrol import enrol
from tactiled.learn.model import (
    PARTNER,
    Model,
    _fingerprint,
    ensemble_scores,
    load_model,
    log_softmax,
    softmax,
    take_columns,
)
from tactiled.learn.search import SPECTRUM, Candidate, accuracy_of
from tactiled.learn.train import train
from tests.conftest import cli_here, run_cli, surfaces_but_one

CANDIDATES = [SPECTRUM, Candidate(("psd",), "linear", 0.25)]  # the linear one is the simpler: it wins within one standard error


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[str]]:
    """An ensemble trained on four of five surfaces (robot scene), its file, and the recordings of all five."""
    root = tmp_path_factory.mktemp("ensemble")
    data, known, surfaces = surfaces_but_one(root, 5, seed=1)
    res = train(known, Config(), folds=2, candidates=CANDIDATES, ensemble="always")
    assert res.model.partner is not None and res.winner == CANDIDATES[1].name
    res.model.save(root / "m.npz")
    return root / "m.npz", data, surfaces


def _windows(model: Model, data: Path, n: int = 6) -> np.ndarray:
    """Raw features (n, F) of the first n windows of one recording, analysed as the daemon does."""
    from tactiled.files.recording import load_recording

    rec = load_recording(sorted(data.glob("*.npz"))[0])
    a, b, _ = rec.slides()[0]
    step = round(model.settings.duration_s * model.fs)
    analyser = Analyser(model.settings, model.fs, rec.volts_per_count, integer=True)
    rows = [analyser.analyse(rec.samples[a + i * step:a + (i + 1) * step]).features for i in range(n)]
    assert all(r is not None for r in rows) and b - a >= n * step
    return np.stack([r for r in rows if r is not None])


def test_an_ensemble_round_trips_lean_and_through_sklearn(trained: tuple[Path, Path, list[str]], tmp_path: Path) -> None:
    path, data, _ = trained
    lean, ref = load_model(path), load_model(path, lean=False)
    assert lean.partner is not None and ref.partner is not None
    assert json.loads(np.load(path)["header"].item())["version"] == 8  # its novelty reads the spectral shape (train's default)
    x = _windows(lean, data)
    for w in (1, 3, 6):
        np.testing.assert_allclose(lean.slide_proba(x[:w]), ref.slide_proba(x[:w]), rtol=0, atol=1e-9)
    assert lean.save(tmp_path / "again.npz") == lean.fingerprint == load_model(tmp_path / "again.npz").fingerprint
    # both members read columns of one analysis: the union of their features, each its own
    assert set(lean.names) == set(lean.inputs) | set(lean.partner.names) and lean.partner.settings.fusion == "features"
    assert "ensemble" in lean.describe() and lean.kind in lean.describe() and lean.partner.kind in lean.describe()
    assert lean.summary["ensemble"]["used"] and math.isfinite(lean.summary["ensemble"]["mean"])
    assert lean.summary["early_calibration"]["prefixes"] > 0 and lean.early_calibration is not None


def test_loading_an_ensemble_imports_neither_sklearn_nor_scipy(trained: tuple[Path, Path, list[str]]) -> None:
    code = (f"import sys; from tactiled.learn.model import load_model; m = load_model({str(trained[0])!r}); "
            "print(type(m.partner.pipeline).__name__, sorted({k.split('.')[0] for k in sys.modules} & {'sklearn', 'scipy'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "LeanPipeline []", out.stdout + out.stderr


def test_ensemble_probabilities_are_the_normalised_product_of_the_members(trained: tuple[Path, Path, list[str]]) -> None:
    path, data, _ = trained
    model = load_model(path)
    assert model.partner is not None
    x = _windows(model, data)
    first = softmax(model.fused_scores(x), model.member_temperature)
    second = model.partner.slide_proba(take_columns(x, model.names, model.partner.names))
    assert model.partner.settings.fusion == "features" and model.settings.fusion == "scores"
    product = (first * second) ** (1.0 / model.temperature)  # the ensemble's own temperature softens the product
    np.testing.assert_allclose(model.slide_proba(x), product / product.sum(), rtol=1e-9, atol=1e-12)
    plain = replace(model, temperature=1.0)
    np.testing.assert_allclose(plain.slide_proba(x), first * second / (first * second).sum(), rtol=1e-9, atol=1e-12)
    assert np.argmax(model.slide_proba(x)) == np.argmax(first * second)
    np.testing.assert_allclose(model.predict_proba(x[:1])[0], model.slide_proba(x[:1]), rtol=1e-12)


def test_a_single_model_is_written_as_format_8_with_the_spectral_novelty_and_6_without(tmp_path: Path) -> None:
    shipped = load_model()  # the shipped file: format 8, its novelty on psd columns its classifier does not read
    assert shipped.partner is None and shipped.novelty_names is not None and set(shipped.inputs) < set(shipped.names)
    shipped.save(tmp_path / "m.npz")
    assert json.loads(np.load(tmp_path / "m.npz")["header"].item())["version"] == 8
    again = load_model(tmp_path / "m.npz")
    assert again.fingerprint == shipped.fingerprint and again.inputs == shipped.inputs and again.novelty_names == shipped.novelty_names
    plain = replace(shipped, settings=replace(shipped.settings, names=shipped.inputs), member_names=None, novelty_names=None,
                    novelty_center=None, novelty_scale=None, novelty_x=None, novelty_y=None, novelty_groups=None, fingerprint="")
    plain.save(tmp_path / "p.npz")
    assert json.loads(np.load(tmp_path / "p.npz")["header"].item())["version"] == 6
    assert load_model(tmp_path / "p.npz").names == shipped.inputs


@pytest.mark.parametrize("signal", ["silent", "saturated", "constant"])
def test_an_ensemble_is_finite_on_extreme_slides(signal: str, trained: tuple[Path, Path, list[str]]) -> None:
    model = load_model(trained[0])
    n = round(model.settings.duration_s * model.fs)
    x = {"silent": np.zeros((n, 2)), "saturated": np.full((n, 2), 32767.0), "constant": np.full((n, 2), 3.0)}[signal]
    window = Analyser(model.settings, model.fs, 1.0, integer=False).analyse(x)
    assert window.features is not None
    for rows in (window.features[None, :], np.stack([window.features] * 4)):
        for final in (True, False):
            proba, confidence, novelty = model.assess(rows, final)
            assert np.all(np.isfinite(proba)) and abs(proba.sum() - 1.0) < 1e-9 and 0.0 <= confidence <= 1.0
            assert novelty is not None and math.isfinite(novelty)


def test_ensemble_scores_with_one_class_left_and_none() -> None:
    inf = -np.inf
    first = np.array([[2.0, inf, inf], [inf, inf, inf], [1e300, -1e300, 0.0], [0.0, 0.0, 0.0]])
    second = np.array([[0.5, 3.0, inf], [inf, inf, inf], [0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]])
    both = ensemble_scores(first, 0.5, second, 2.0)
    assert both[0, 0] == pytest.approx(np.log(softmax(np.array([0.5, 3.0]), 2.0)[0])) and np.all(both[0, 1:] == inf)  # one class left
    assert np.all(both[1] == inf)  # no score: no class is more likely, and the slide counts as undecided
    assert np.all(np.isfinite(both[2])) and np.argmax(both[2]) == 0  # huge scores stay finite
    assert both[3, 0] == inf and np.all(np.isfinite(both[3, 1:]))  # NaN: the least likely class
    assert accuracy_of(both, np.array([0, 0, 0, 1])) == 0.75  # the undecided slide is wrong
    p = softmax(both, 1.3)
    assert np.all(np.isfinite(p)) and np.allclose(p.sum(axis=1), 1.0) and p[0, 0] == 1.0
    lp = log_softmax(np.array([[1e308, -1e308, 0.0]]), 1e-6)
    assert np.isfinite(lp).all() and lp[0, 0] == 0.0


def test_enrol_refits_both_members_of_an_ensemble(trained: tuple[Path, Path, list[str]], tmp_path: Path) -> None:
    path, data, surfaces = trained
    old = load_model(path)
    new = sorted(data.glob(f"*_{surfaces[4]}_*.npz"))
    done = enrol(path, new, Config(), label="NEW")
    m = done.model
    assert m.partner is not None and old.partner is not None and done.added == {"NEW": 6}
    assert m.classes == sorted([*old.classes, "NEW"]) and m.partner.classes == m.classes
    assert m.refit is not None and m.partner.refit is not None and list(m.partner.refit[1]).count("NEW") == 6  # one row per slide
    assert (m.temperature, m.member_temperature, m.partner.temperature) == (old.temperature, old.member_temperature, old.partner.temperature)
    m.save(tmp_path / "m2.npz")
    again = load_model(tmp_path / "m2.npz")
    assert again.partner is not None and again.names == old.names
    res = run_cli("replay", "--json", "--model", str(tmp_path / "m2.npz"), *map(str, new))
    finals = [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{") and '"final": true' in line]
    assert finals and sum(f.get("label") == "NEW" for f in finals) >= len(finals) - 1, res.stdout[-2000:] + res.stderr


def _rewritten(model: Model, path: Path, arrays_change: dict, header_change: dict | None = None) -> Path:
    arrays = {**model._arrays(), **model._trust_arrays(), **arrays_change}
    arrays = {k: v for k, v in arrays.items() if v is not None}
    header = {**model._header(), **(header_change or {})}
    header["fingerprint"] = _fingerprint(header, arrays)
    atomic_savez(path, {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
    return path


@pytest.mark.parametrize(("arrays", "header", "message"), [
    ({PARTNER + "scaler_mean": np.full(3, np.nan)}, None, "partner_scaler_mean: must be"),
    ({PARTNER + "train_x": None}, None, "partner_train_x: missing"),
    ({PARTNER + "svm_gamma": np.float64(-1.0)}, None, "partner_svm_support, svm_n_support"),
    ({PARTNER + "weights": np.zeros(3)}, None, "partner_weights: not an array"),
    ({}, {"partner": {"names": ["film9.psd.x"]}}, "header.ensemble.partner.names: must be distinct feature names"),
    ({}, {"partner": {"temperature": 0.0}}, "header.ensemble.partner.temperature: must be a finite number"),
    ({}, {"partner": {"classifier": "forest"}}, "header.ensemble.partner.classifier: unknown 'forest'"),
    ({}, {"partner": {"params": {"C": -1.0}}}, "header.ensemble.partner.params.C: must be a number"),
    ({}, {"member": {"temperature": math.nan}}, "header.ensemble.member.temperature: must be a finite number"),
])
def test_a_corrupt_member_is_refused_in_one_line_naming_the_file(arrays: dict, header: dict | None, message: str,
                                                                 trained: tuple[Path, Path, list[str]], tmp_path: Path) -> None:
    model = load_model(trained[0])
    ens = model._header()["ensemble"]
    change = {"ensemble": {k: {**v, **(header or {}).get(k, {})} for k, v in ens.items()}} if header else None
    bad = _rewritten(model, tmp_path / "bad.npz", arrays, change)
    with pytest.raises(ModelError) as info:
        load_model(bad)
    text = str(info.value)
    assert "\n" not in text and str(bad) in text and message in text, text


def test_train_prints_the_ensemble_beside_the_choice(trained: tuple[Path, Path, list[str]], tmp_path: Path,
                                                     capfd: pytest.CaptureFixture[str]) -> None:
    _, data, surfaces = trained
    known = [str(p) for p in sorted(data.glob("*.npz")) if f"_{surfaces[4]}_" not in p.name]
    res = cli_here(capfd, "train", *known, "-o", str(tmp_path / "m.npz"), "--ensemble", "always", "--folds", "2")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    chosen = next(i for i, line in enumerate(lines) if line.startswith("* "))
    assert lines[chosen + 1].lstrip().startswith("+ spectrum / svm / 0.25 s / slide mean") and "as an ensemble: the model" in lines[chosen + 1]
    assert "with spectrum / svm / 0.25 s / slide mean (ensemble)" in res.stderr  # the winner line
    model = load_model(tmp_path / "m.npz")
    assert model.partner is not None and f"{model.describe()}; fingerprint {model.fingerprint}" in lines[-2]  # the last: another unit
    assert "the choice alone's (the model is it and its ensemble partner)" in lines[-1]  # its gain figure is the choice's alone
    assert any(line.startswith("nested CV per surface (recall of the model on recordings") for line in lines)  # the ensemble's


def test_the_winner_kept_beside_an_ensemble_is_the_model_without_one(trained: tuple[Path, Path, list[str]]) -> None:
    _, data, surfaces = trained
    known = [p for p in sorted(data.glob("*.npz")) if f"_{surfaces[4]}_" not in p.name]
    both = train(known, Config(), folds=2, candidates=CANDIDATES, ensemble="always", keep_models=True)
    off = train(known, Config(), folds=2, candidates=CANDIDATES, ensemble="off").model
    alone = both.models[both.winner]
    assert both.model.partner is not None and alone.partner is None and off.partner is None and "ensemble" not in off.summary
    assert alone.early_calibration == off.early_calibration is not None and alone.temperature == off.temperature
    x = _windows(off, data)
    np.testing.assert_array_equal(alone.slide_proba(x), off.slide_proba(x))


def test_assess_many_is_assess_of_each_slide_bit_for_bit(trained: tuple[Path, Path, list[str]]) -> None:
    """Replay assesses every prefix of every slide in one call (Model.assess_many): each row must be assess's of those
    windows alone, bit for bit (the ensemble's, not its first member's), for both fusions, lean and scikit-learn."""
    path, data, _ = trained
    x = _windows(load_model(path), data, n=6)
    rows = [(0, i) for i in range(1, 7)] + [(2, 5), (5, 6), (0, 6)]
    for model in (load_model(path), load_model(path, lean=False)):
        assert model.partner is not None
        for fusion in ("features", "scores"):
            fused = replace(model, settings=replace(model.settings, fusion=fusion),
                            partner=replace(model.partner, settings=replace(model.partner.settings, fusion=fusion)))
            for final in (True, False):
                proba, confidence, novelty = fused.assess_many(x, rows, final)
                for i, (lo, hi) in enumerate(rows):
                    p, c, n = fused.assess(x[lo:hi], final)
                    assert np.array_equal(proba[i], p) and confidence[i] == c and novelty[i] == n, (fusion, final, lo, hi)


def test_an_ensemble_states_its_own_nested_accuracy_not_its_first_members(trained: tuple[Path, Path, list[str]]) -> None:
    """With --ensemble always the file's cv_accuracy (and the line describe() prints from it) was the winner alone's nested
    estimate, beside the ensemble's own CV accuracy. Now it is the ensemble's (each outer fold's pick with its partner); the
    winner alone's is kept under ensemble.alone_nested, and a file without the mark says whose it is."""
    path, _, _ = trained
    model = load_model(path)
    cv, ens = model.summary["cv_accuracy"], model.summary["ensemble"]
    assert cv["model"] == "ensemble" and ens["alone_nested"]["picks"] == cv["picks"] and "model" not in ens["alone_nested"]
    assert cv["mean"] == pytest.approx(np.mean(cv["folds"]))
    if all(p == model.summary["winner"] for p in cv["picks"]):  # the same member in every fold: the ensemble's own folds
        assert cv["folds"] == pytest.approx(ens["folds"])
    assert f"nested CV accuracy {100 * cv['mean']:.1f} ±" in model.describe()
    old = replace(model, summary={**model.summary, "cv_accuracy": ens["alone_nested"]})  # a file from before the mark
    assert "nested CV accuracy of its first member alone" in old.describe(), old.describe()


def test_ensemble_always_says_when_there_is_no_ensemble_to_make(trained: tuple[Path, Path, list[str]]) -> None:
    """The winner was the spectral candidate itself: --ensemble always did nothing without a word."""
    _, data, surfaces = trained
    known = [p for p in sorted(data.glob("*.npz")) if f"_{surfaces[4]}_" not in p.name][:4]  # two surfaces
    said: list[str] = []
    res = train(known, Config(), folds=2, candidates=[SPECTRUM], ensemble="always", progress=said.append)
    assert res.model.partner is None
    assert f"--ensemble always: no ensemble: the choice is {SPECTRUM.name} itself" in said, said
