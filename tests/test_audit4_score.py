"""tactiled score against an outside audit: a recording given twice (or a copy of it) is refused as train refuses it, and a
surface named "-" keeps its row, its column and its recall line (score's no-label column was named "-" too)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here


@pytest.fixture(scope="module")
def dashed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """A quick model of two surfaces, one of them named "-", and the recordings it was trained on (2 files of 2 slides each)."""
    root = tmp_path_factory.mktemp("dashed")
    files = sorted(write_dataset(root / "sim", scene="robot", surfaces="2", files_per_surface=2, slides_per_file=2))
    first = str(np.load(files[0])["surface"][0])
    for f in files:
        with np.load(f) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["surface"] = np.array(["-" if s == first else s for s in arrays["surface"].astype(str)])
        np.savez(f, **arrays)
    model = root / "m.npz"
    res = cli_here(None, "train", *map(str, files), "-o", str(model), "--method", "quick", "--folds", "2")
    assert res.returncode == 0, res.stderr
    return model, files


def test_a_surface_named_dash_keeps_its_row_column_and_recall_line(dashed: tuple[Path, list[Path]], capfd: pytest.CaptureFixture[str]) -> None:
    """Its row was all zeros and its recall line missing: the slides counted in the matrix no longer added up to n."""
    model, files = dashed
    res = cli_here(capfd, "score", str(model), *map(str, files), "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    classes, cm = report["classes"], np.array(report["confusion"])
    surfaces = classes[:-1]  # rows; the last column: no label
    assert "-" in surfaces and len(set(classes)) == len(classes), classes  # no surface's column is the no-label one
    assert cm.shape == (len(surfaces), len(classes)) and cm.sum() == report["n"] > 0
    assert cm[surfaces.index("-")].sum() > 0 and set(report["recall"]) == set(surfaces)
    assert cm[:, -1].sum() == report["n"] - report["labelled"]  # the last column: the slides given no label
    assert int(np.trace(cm[:, :-1])) == report["correct"]
    printed = cli_here(capfd, "score", str(model), *map(str, files))
    assert printed.returncode == 0, printed.stderr
    recall_lines = [line.split(":")[0].strip() for line in printed.stdout.splitlines() if ": recall " in line]
    assert sorted(recall_lines) == sorted(surfaces), printed.stdout


@pytest.mark.parametrize("how", ["twice", "symlink", "copy", "file label twice"])
def test_a_recording_given_twice_is_refused_as_train_refuses_it(how: str, dashed: tuple[Path, list[Path]], tmp_path: Path,
                                                                 capfd: pytest.CaptureFixture[str]) -> None:
    """score $M a.npz a.npz counted its slides twice (4 of 6 where alone 2 of 3) and exited 0. A recording with a file label
    alone is refused once the replay found slides in it (two files of silence count nothing: tests/test_hostile_files.py)."""
    from tactiled.files.recording import Recording, load_recording, save_recording

    model, files = dashed
    first = files[0]
    if how == "file label twice":
        truth = load_recording(files[0])
        first = tmp_path / "label.npz"
        save_recording(first, Recording(truth.samples, truth.fs, truth.volts_per_count, label=str(truth.surface[0])))
    again = first
    if how == "symlink":
        again = tmp_path / "link.npz"
        again.symlink_to(files[0])
    elif how == "copy":
        again = tmp_path / "copy.npz"
        shutil.copy(files[0], again)
    res = cli_here(capfd, "score", str(model), str(first), str(again), "--json")
    assert res.returncode == 2 and res.stdout == "", res.stdout
    error = [line for line in res.stderr.splitlines() if line.strip()][-1]  # after the replays' progress line, for a file label
    assert error == (f"tactiled: error: {first} and {again} hold the same samples: one recording would count as two "
                     "(its slides would count twice in the accuracy); give each recording once"), res.stderr
    train = cli_here(capfd, "train", str(first), str(again), *map(str, files[1:]), "-o", str(tmp_path / "m2.npz"), "--method", "quick")
    # the same check, in words for train: what a copy would do to its cross-validation
    assert train.returncode == 2 and train.stderr.splitlines()[-1] == error.replace("its slides would count twice in the accuracy",
                                                                                    "cross-validation would test it on its own copy")


def test_scores_interval_says_when_it_is_the_rule_of_three() -> None:
    """An outside audit: 15 of 15 right on 3 recordings showed "95 % interval over recordings 0.0000-1.0000" unexplained."""
    from tactiled.cli.cmd_learn import interval_clause

    assert interval_clause([0.0, 1.0], 15, 15) == ", 95 % interval over recordings 0.0000-1.0000 (every slide right: the rule of three, 1 - 3/recordings)"
    assert interval_clause([0.0, 0.75], 0, 12).endswith("(every slide wrong: the rule of three, 3/recordings)")
    assert interval_clause([0.5, 0.9], 10, 15) == ", 95 % interval over recordings 0.5000-0.9000" and interval_clause(None, 3, 3) == ""
