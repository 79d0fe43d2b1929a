"""tactiled enrol: a surface added to a trained model from a few slides, the input model untouched, a record in the header."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tactiled.config import Config
from tactiled.errors import TactiledError
from tactiled.learn.enrol import enrol
from tactiled.learn.model import load_model
from tests.conftest import cli_here, surfaces_but_one


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[str]]:
    """A model trained on two of three surfaces (robot scene), and the folder holding the recordings of all three.

    Every command of this module is run by main() in the test's process (cli_here): the same handlers, lines and files,
    without a new interpreter and worker pool for each."""
    root = tmp_path_factory.mktemp("enrol")
    data, known, surfaces = surfaces_but_one(root, 3, seed=4)
    res = cli_here(None, "train", *map(str, known), "-o", str(root / "m.npz"), "--method", "quick", "--folds", "2")
    assert res.returncode == 0, res.stderr
    return root / "m.npz", data, surfaces


def test_enrol_adds_a_surface_from_six_slides_and_labels_it(trained: tuple[Path, Path, list[str]], tmp_path: Path,
                                                            capfd: pytest.CaptureFixture[str]) -> None:
    model, data, surfaces = trained
    new = sorted(str(p) for p in data.glob(f"*_{surfaces[2]}_*.npz"))
    before = model.read_bytes()
    res = cli_here(capfd, "enrol", str(model), *new, "--label", "NEW", "-o", str(tmp_path / "m2.npz"))
    assert res.returncode == 0, res.stderr
    assert "NEW: 6 slides (a new surface)" in res.stdout
    assert model.read_bytes() == before  # the input is never changed
    old, m2 = load_model(model), load_model(tmp_path / "m2.npz")
    assert m2.classes == sorted([*old.classes, "NEW"]) and m2.fingerprint != old.fingerprint
    record = m2.summary["enrolled"][-1]
    assert record == {"from": old.fingerprint, "slides": {"NEW": 6}, "files": [Path(p).name for p in new]}
    assert m2.novelty_y is not None and list(m2.novelty_y).count("NEW") == 6
    # the threshold fitted again on the new slides, at the share of untaught slides the model was trained with
    assert m2.summary["novelty"]["known_rejected"] is not None and m2.summary["novelty"]["untaught"] == old.summary["novelty"]["untaught"] == 0.1
    assert old.summary["early_calibration"]["prefixes"] > 0 and m2.early_calibration == old.early_calibration  # fitted in training, kept
    relabelled = cli_here(capfd, "replay", "--json", "--model", str(tmp_path / "m2.npz"), *new)
    finals = [json.loads(line) for line in relabelled.stdout.splitlines() if line.startswith("{") and '"final": true' in line]
    assert finals and sum(m.get("label") == "NEW" for m in finals) >= len(finals) - 1


def test_enrol_refuses_too_few_slides_the_input_as_output_and_an_empty_label(trained: tuple[Path, Path, list[str]], tmp_path: Path,
                                                                            capfd: pytest.CaptureFixture[str]) -> None:
    model, data, surfaces = trained
    one = sorted(str(p) for p in data.glob(f"*_{surfaces[2]}_*.npz"))[:1]
    res = cli_here(capfd, "enrol", str(model), *one, "--label", "NEW", "-o", str(tmp_path / "m2.npz"))
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "NEW (3)" in res.stderr and "at least 5" in res.stderr, res.stderr
    assert not (tmp_path / "m2.npz").exists()
    same = cli_here(capfd, "enrol", str(model), *one, "--label", "NEW", "-o", str(model), "--force")
    assert same.returncode == 2 and "never changes its input" in same.stderr
    with pytest.raises(TactiledError, match="--label: must not be empty"):
        enrol(model, one, Config(), label=" ")
    twice = cli_here(capfd, "enrol", str(model), *one, *one, "--label", "NEW", "-o", str(tmp_path / "m2.npz"))  # 6 slides, but 3 twice
    assert twice.returncode == 2 and "hold the same samples" in twice.stderr and not (tmp_path / "m2.npz").exists(), twice.stderr


def test_enrol_adds_slides_of_known_surfaces_by_their_own_labels(trained: tuple[Path, Path, list[str]], tmp_path: Path) -> None:
    """Without --label (recordings of known surfaces, e.g. from another unit of the sensor): rows added to those classes."""
    model, _, surfaces = trained
    from tactiled.sim.simulate import write_dataset

    write_dataset(tmp_path / "new", scene="robot", surfaces="3", files_per_surface=2, slides_per_file=3, seed=5)  # not the learnt ones
    known = sorted(str(p) for p in (tmp_path / "new").glob(f"*_{surfaces[0]}_*.npz"))
    done = enrol(model, known, Config())
    assert done.added == {surfaces[0]: 6} and done.new_classes == [] and done.model.classes == load_model(model).classes
    assert done.model.refit is not None and list(done.model.refit[1]).count(surfaces[0]) > list(load_model(model).refit[1]).count(surfaces[0])


def test_train_novelty_distance_is_kept_in_the_file_and_through_enrolment(trained: tuple[Path, Path, list[str]], tmp_path: Path,
                                                                          capfd: pytest.CaptureFixture[str]) -> None:
    """train --novelty distance: the file says so, its threshold is fitted on that score, and enrol keeps the score it was trained with
    (and refits the default spectrum test's distance threshold on the spectral shape, with no ratio test: the default model's
    file says combined, its summary spectrum)."""
    model, data, surfaces = trained
    known = [str(p) for p in sorted(data.glob("*.npz")) if f"_{surfaces[2]}_" not in p.name]
    res = cli_here(capfd, "train", *known, "-o", str(tmp_path / "d.npz"), "--method", "quick", "--folds", "2", "--novelty", "distance")
    assert res.returncode == 0, res.stderr
    combined, distance = load_model(model), load_model(tmp_path / "d.npz")
    assert (combined.novelty_score, distance.novelty_score) == ("combined", "distance")
    assert distance.summary["novelty"]["score"] == "distance" and distance.novelty_threshold != combined.novelty_threshold
    assert combined.summary["novelty"]["distance_threshold"] == combined.novelty_distance_threshold < float("inf")
    assert combined.summary["novelty"]["score"] == "spectrum" and combined.novelty_threshold == float("inf")
    assert combined.novelty_names is not None and distance.novelty_names is None
    new = sorted(str(p) for p in data.glob(f"*_{surfaces[2]}_*.npz"))
    assert cli_here(capfd, "enrol", str(tmp_path / "d.npz"), *new, "--label", "NEW", "-o", str(tmp_path / "d2.npz")).returncode == 0
    assert load_model(tmp_path / "d2.npz").novelty_score == "distance"
    assert cli_here(capfd, "enrol", str(model), *new, "--label", "NEW", "-o", str(tmp_path / "c2.npz")).returncode == 0
    enrolled = load_model(tmp_path / "c2.npz")
    assert enrolled.novelty_score == "combined" and enrolled.summary["novelty"]["distance_threshold"] == enrolled.novelty_distance_threshold
    assert enrolled.summary["novelty"]["score"] == "spectrum" and enrolled.novelty_threshold == float("inf")  # enrolment adds no ratio test
    assert enrolled.novelty_names == combined.novelty_names and enrolled.novelty_x is not None and enrolled.novelty_x.shape[1] == len(combined.novelty_names)
    assert enrolled.novelty_distance_threshold != combined.novelty_distance_threshold  # refitted with the new surface's slides
    bad = cli_here(capfd, "train", *known, "-o", str(tmp_path / "x.npz"), "--novelty", "cosine")
    assert bad.returncode == 2 and "--novelty" in bad.stderr


def test_an_enrolled_model_states_its_accuracy_as_the_base_models(trained: tuple[Path, Path, list[str]]) -> None:
    """enrol keeps the summary of the model it started from, and the new model's line printed that model's nested CV accuracy
    as its own. Also: train's winner line and the model's line rounded one interval two ways (0.925: "0.93-1.00" and "92–100 %")."""
    from dataclasses import replace

    from tactiled.learn.search import _interval_text

    model, data, surfaces = trained
    base = load_model(model)
    done = enrol(model, sorted(str(p) for p in data.glob(f"*_{surfaces[2]}_*.npz")), Config(), label="NEW")
    line = done.model.describe()
    assert "nested CV accuracy" in base.describe() and "base model" not in base.describe()
    assert "the base model's nested CV accuracy" in line and line.endswith("(from before enrolment: not measured with the slides enrolled)")
    cv = {**base.summary["cv_accuracy"], "interval95": [0.925, 1.0]}
    assert _interval_text([0.925, 1.0]) == " (95 % interval over recordings 92–100 %)"
    assert _interval_text([0.925, 1.0]) in replace(base, summary={**base.summary, "cv_accuracy": cv}).describe()


def test_enrol_refuses_to_grow_a_model_past_the_classes_a_file_may_hold(trained: tuple[Path, Path, list[str]], tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """An audit enrolled a 10 000-class model into one of 10 001 that every later command refused: the limit is checked
    before anything is fitted or written (the limit lowered to the model's own 2 classes here)."""
    model, data, surfaces = trained
    new = sorted(str(p) for p in data.glob(f"*_{surfaces[2]}_*.npz"))
    monkeypatch.setattr("tactiled.learn.enrol.MAX_CLASSES", 2)
    with pytest.raises(TactiledError, match=r"^enrolment would give the model 3 classes, more than the 2 a model file may hold"):
        enrol(model, new, Config(), label="NEW")
