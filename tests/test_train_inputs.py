"""What train and enrol are given: surface names a recording may carry, surfaces none of whose slides has a usable window,
and the wording of a model cross-validated by slide. Each case was a silent loss or a misleading line (found by an audit).

Real files in a temporary folder: two simulated surfaces (robot scene, 2 files of 3 slides each) and "Tiny", two files of
constant samples whose slides are 10 samples long, too short for any window (``window_too_short``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tactiled.cli.main import main
from tactiled.config import Config
from tactiled.errors import RecordingError, TactiledError
from tactiled.files.recording import Recording, load_recording, save_recording
from tactiled.learn.enrol import enrol
from tactiled.learn.search import quick_candidates
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset

TINY = "Tiny: 0 of 6 slides usable (window_too_short 6)"


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], list[str]]:
    """(the paths of the two simulated surfaces, the paths of Tiny's two files)."""
    root = tmp_path_factory.mktemp("inputs")
    good = write_dataset(root, scene="robot", surfaces="2", files_per_surface=2, slides_per_file=3)
    rec = load_recording(good[0])
    tiny = []
    for i in range(2):  # two distinct recordings (a copy would be refused as one recording twice)
        path = root / f"tiny_{i}.npz"
        save_recording(path, Recording(samples=np.full((20000, rec.channels), 100 + i, dtype=np.int16), fs=rec.fs,
                                       volts_per_count=rec.volts_per_count, slide_start=np.array([1000, 5000, 9000]),
                                       slide_stop=np.array([1010, 5010, 9010]), surface=np.array(["Tiny"] * 3)))
        tiny.append(str(path))
    return [str(p) for p in good], tiny


def _tiny(path: Path, **arrays: object) -> Path:
    """A small valid recording with ``arrays`` (label, or slides with surface)."""
    np.savez(path, samples=np.zeros((1000, 2), dtype=np.int16), fs=np.float64(20000), **arrays)  # type: ignore[arg-type]
    return path


@pytest.mark.parametrize(("key", "names"), [
    ("label", ""), ("label", "   "), ("label", "a\nb"), ("label", "P120\x1b[2J"), ("label", "a\u2028b"),
    ("surface", ["A", ""]), ("surface", [" \t", "A"]), ("surface", ["A", "b\rc"]), ("label", "P120 "), ("surface", ["P120", " P120"]),
])
def test_a_blank_name_or_one_with_a_control_character_is_refused_at_load(key: str, names: str | list[str], tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """"" is training's unlabelled marker (such a surface was listed, then left out of the model while its slides counted in
    the nested estimate); a newline or an escape broke replay's and score's one line per slide. One line naming file and key,
    exit 2."""
    arrays: dict[str, object] = {"label": np.str_(names)} if key == "label" else {
        "slide_start": np.array([100, 500]), "slide_stop": np.array([300, 700]), "surface": np.array(names)}
    path = _tiny(tmp_path / "bad.npz", **arrays)
    assert load_recording(_tiny(tmp_path / "ok.npz", label=np.str_("Papier P120 é"))).label == "Papier P120 é"  # spaces inside: a name
    with pytest.raises(RecordingError, match=f"^{path}: {key}: "):
        load_recording(path)
    code = main(["replay", "--no-model", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"tactiled: error: {path}: {key}: "), err


@pytest.mark.parametrize("label", ["a\nb", "x" * 5000])
def test_enrol_label_follows_the_rule_of_a_recordings_label(label: str, data: tuple[list[str], list[str]]) -> None:
    """enrol --label took 5000 characters and "a\\nb": names a recording may not carry."""
    with pytest.raises(TactiledError, match=r"^--label: "):
        enrol(None, data[1], Config(), label=label)


def test_train_refuses_a_surface_with_no_usable_window_naming_it_and_why(data: tuple[list[str], list[str]],
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Tiny passed the slide table (6 slides, 2 files), had no window, and was left out of the model silently (exit 0,
    dropped [], its slides counted wrong in the nested estimate). Now: one line naming it, exit 2, nothing written."""
    good, tiny = data
    with pytest.raises(TactiledError, match=r"too few slides with a usable window \(< 2\): Tiny: 0 of 6 slides usable \(window_too_short 6\)"):
        train([*good, *tiny], Config(), method="quick")
    out = Path(tiny[0]).parent / "m.npz"
    code = main(["train", *good, *tiny, "-o", str(out), "--method", "quick"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("tactiled: error: too few slides with a usable window") and TINY in err[-1], err
    assert f"train:   {TINY}" in err and any("slides without a usable" in line and "window_too_short 6" in line for line in err), err
    assert not out.exists()


def test_drop_rare_trains_without_a_surface_with_no_usable_window_and_records_it(data: tuple[list[str], list[str]]) -> None:
    good, tiny = data
    said: list[str] = []
    res = train([*good, *tiny], Config(), drop_rare=True, candidates=quick_candidates()[:1], folds=2, progress=said.append)
    assert res.model.summary["dropped"] == ["Tiny"] and "Tiny" not in res.model.classes and len(res.model.classes) == 2
    assert "training without Tiny (--drop-rare): too few slides with a usable window" in said, said
    assert res.slides == 12 and "Tiny" not in res.per_class  # its slides no longer count (as wrong) in the estimate
    assert res.nested["mean"] == pytest.approx(np.mean(res.nested["folds"]))


def test_enrol_says_too_few_usable_slides_not_no_labels(data: tuple[list[str], list[str]]) -> None:
    """Labelled slides, none usable: it said "the recordings carry no labels ... pass --label NAME"."""
    with pytest.raises(TactiledError, match=r"too few usable slides for Tiny \(0 of 6 slides usable\).*window_too_short 6") as err:
        enrol(None, data[1], Config())
    assert "carry no labels" not in str(err.value)


def test_enrol_refuses_a_surface_with_no_usable_slide_beside_a_good_one(data: tuple[list[str], list[str]]) -> None:
    """With a usable surface beside it, Tiny was left out of the enrolment without a word."""
    good, tiny = data
    first = sorted(good)[:2]  # one surface: 2 files of 3 slides
    with pytest.raises(TactiledError, match=r"too few usable slides for Tiny \(0 of 6 slides usable\)"):
        enrol(None, [*first, *tiny], Config())


def test_a_model_grouped_by_slide_says_its_interval_is_over_slides_and_optimistic(data: tuple[list[str], list[str]]) -> None:
    """The nested estimate of --group-by slide resamples slides, not recordings; train's winner line said "over recordings"."""
    good, _ = data
    said: list[str] = []
    res = train(good, Config(), group_by="slide", candidates=quick_candidates()[:1], folds=2, progress=said.append)
    assert res.nested["grouped_by"] == "slide" and res.model.summary["cv_accuracy"]["grouped_by"] == "slide"
    winner = next(line for line in said if line.startswith("winner "))
    assert "over recordings" not in winner and "optimistic" in winner, winner
    assert res.nested["interval95"] is None or "interval over slides" in winner, winner
    assert any(line.startswith("warning: --group-by slide") and "optimistic" in line for line in said), said
    line = res.model.describe()  # the model file's own line (tactiled replay, run, check-config say it)
    assert "over recordings" not in line and "optimistic (train --group-by slide" in line, line


def test_a_surface_whose_label_only_files_give_no_slide_is_named_not_dropped_silently(data: tuple[list[str], list[str]], tmp_path: Path,
                                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Two files labelled Glass in which the detector finds no slide (silence; noise too short for a slide): Glass was missing
    from the slide table and from the model, nothing named it, exit 0. Now each file is named in one line, Glass is listed with
    0 slides and the min-slides rule names it (exit 2); --drop-rare trains without it, saying so."""
    good, _ = data
    glass = [str(tmp_path / "glass_a.npz"), str(tmp_path / "glass_b.npz")]
    rng = np.random.default_rng(0)
    np.savez(glass[0], samples=np.zeros((40000, 2), np.int16), fs=np.float64(20000), label=np.str_("Glass"))
    np.savez(glass[1], samples=rng.integers(-300, 300, (2800, 2)).astype(np.int16), fs=np.float64(20000), label=np.str_("Glass"))
    out = tmp_path / "m.npz"
    code = main(["train", *good, *glass, "-o", str(out), "--method", "quick"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not out.exists(), err
    assert "train:   Glass: 0, 0, 0" in err, err
    assert all(f"train: no slide detected in {g} (label Glass)" in err for g in glass), err
    assert err[-1].startswith("tactiled: error: too few slides (< 2) for surface(s) Glass (0 slides)") and "group-by" not in err[-1], err
    said: list[str] = []
    res = train([*good, *glass], Config(), drop_rare=True, candidates=quick_candidates()[:1], folds=2, progress=said.append)
    assert res.model.summary["dropped"] == ["Glass"] and "Glass" not in res.model.classes, res.model.summary["dropped"]
    assert "training without Glass (0 slides) (--drop-rare)" in said, said


def test_train_says_slides_of_a_recording_without_a_surface_are_not_learnt(data: tuple[list[str], list[str]],
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A recording that names no surface among labelled ones: its slides were said to be "without a usable window:
    unlabelled N", as if their windows had failed. Now they are said to have no surface."""
    good, _ = data
    rec = load_recording(good[0])
    bare = Path(good[0]).parent / "bare.npz"
    save_recording(bare, Recording(samples=(-rec.samples.astype(np.int32)).clip(-32768, 32767).astype(np.int16), fs=rec.fs,
                                   volts_per_count=rec.volts_per_count))
    out = bare.parent / "bare_model.npz"
    code = main(["train", *good, str(bare), "-o", str(out), "--method", "quick"])
    err = capsys.readouterr().err.splitlines()
    assert code == 0, err
    assert any("slides without a surface (their recordings name none) are not learnt" in line for line in err), err
    assert not any("unlabelled" in line for line in err), err
    # which recording (an outside audit: a lab that forgot --label on one record did not learn which)
    assert any(f"{bare}: no label and no per-slide truth (recorded without --label?)" in line for line in err), err


def test_by_slide_a_surface_of_one_slide_is_refused(data: tuple[list[str], list[str]], tmp_path: Path) -> None:
    """``--group-by slide --min-slides 1`` on one slide per surface: no fold can test a surface on a slide it did not learn
    from. It wrote a model ("nested CV 0.0 %", every confidence 0.5) and exited 0 (an outside review); now one line naming
    the surfaces."""
    good, _ = data
    one = []
    for path in sorted(good)[::2]:  # one recording of each surface, its first slide alone
        rec = load_recording(path)
        assert rec.slide_start is not None and rec.slide_stop is not None and rec.surface is not None
        single = replace(rec, slide_start=rec.slide_start[:1], slide_stop=rec.slide_stop[:1], surface=rec.surface[:1],
                         ra_um=None if rec.ra_um is None else rec.ra_um[:1])
        one.append(str(tmp_path / Path(path).name))
        save_recording(one[-1], single)
    with pytest.raises(TactiledError, match=r"have a single usable slide: cross-validation grouped by slide cannot test them"):
        train(one, Config(), group_by="slide", min_slides=1, candidates=quick_candidates()[:1], folds=2)
