"""score: slides of surfaces the model was never taught are scored apart from the taught ones, and together as open set."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tactiled.core.events import SlideResult
from tactiled.files.recording import Recording, load_recording, save_recording
from tactiled.learn.score import score
from tactiled.sim.simulate import write_dataset
from tests.conftest import REPO, cli_here

MODEL = str(REPO / "tactiled" / "data" / "default_model.npz")


def test_untaught_slides_leave_the_headline_and_count_right_in_the_open_set_when_called_unknown(tmp_path: Path) -> None:
    """Taught a only: its slide right; of b's two slides one called unknown (right for it), one labelled a (wrong)."""
    rec = Recording(np.zeros((200, 1), dtype=np.int16), 1000.0, slide_start=np.array([0, 60, 130]), slide_stop=np.array([50, 120, 190]),
                    surface=np.array(["a", "b", "b"]))
    save_recording(tmp_path / "r.npz", rec)
    rec = load_recording(tmp_path / "r.npz")
    right = SlideResult(0, 2, 48, (2, 48), "a", None, 0.9, [("a", 0.9)], {})
    unknown = SlideResult(1, 62, 118, (62, 118), None, "unknown_surface", 0.4, [("a", 0.4)], {})
    wrong = SlideResult(2, 132, 188, (132, 188), "a", None, 0.8, [("a", 0.8)], {})
    report = score([("r", rec)], [[right, unknown, wrong]], ["a"])
    assert (report["taught_n"], report["taught_correct"], report["taught_accuracy"]) == (1, 1, 1.0)  # the headline: b is not in it
    assert (report["untaught_n"], report["untaught_unknown"], report["untaught_unknown_share"]) == (2, 1, 0.5)
    assert (report["open_set_correct"], report["open_set_accuracy"]) == (2, pytest.approx(2 / 3))
    # the keys the benches read keep their meaning: right labels over every slide, untaught ones wrong
    assert (report["n"], report["correct"], report["accuracy"], report["untaught"]) == (3, 1, pytest.approx(1 / 3), {"b": [2, 1]})
    only_untaught = score([("r", rec)], [[unknown]], ["c"])  # no taught slide: no headline accuracy, not 0 of 0
    assert only_untaught["taught_accuracy"] is None and only_untaught["taught_n"] == 0 and only_untaught["open_set_correct"] == 1
    assert only_untaught["labelled"] == 0 and only_untaught["accuracy_of_labelled"] is None  # no label: no accuracy of them, not 0.0


def _taught_and_untaught(tmp_path: Path) -> tuple[Path, Path]:
    """Two simulated recordings of two slides each: one of a surface the shipped model was taught, one of "Unseen"."""
    taught, other = write_dataset(tmp_path / "sim", scene="robot", surfaces="2", files_per_surface=1, slides_per_file=2)
    rec = load_recording(other)
    untaught = tmp_path / "untaught.npz"
    save_recording(untaught, Recording(rec.samples, rec.fs, rec.volts_per_count, slide_start=rec.slide_start, slide_stop=rec.slide_stop,
                                       surface=np.array(["Unseen"] * len(rec.slides()))))
    return taught, untaught


def test_score_json_of_a_taught_and_an_untaught_recording(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """The shipped model over a simulated recording of a surface it was taught and one of a surface named as no class of it."""
    taught, untaught = _taught_and_untaught(tmp_path)
    res = cli_here(capfd, "score", MODEL, str(taught), str(untaught), "--json", "--jobs", "1")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    files = {Path(f["file"]).name: f for f in out["files"]}
    assert (out["taught_n"], out["untaught_n"]) == (2, 2)
    assert out["taught_correct"] == files[taught.name]["correct"] and out["taught_accuracy"] == out["taught_correct"] / 2
    unknown = out["untaught"]["Unseen"][1]
    assert out["untaught_unknown"] == unknown and out["untaught_unknown_share"] == unknown / 2
    assert out["open_set_correct"] == out["taught_correct"] + unknown and out["open_set_accuracy"] == out["open_set_correct"] / 4
    assert out["accuracy"] == out["correct"] / 4 and out["correct"] == out["taught_correct"]  # as before: untaught slides wrong in it


def test_score_prints_the_taught_accuracy_as_headline_and_the_untaught_slides_apart(tmp_path: Path,
                                                                                    capfd: pytest.CaptureFixture[str]) -> None:
    files = list(map(str, _taught_and_untaught(tmp_path)))
    out = json.loads(cli_here(capfd, "score", MODEL, *files, "--json", "--jobs", "1").stdout)
    res = cli_here(capfd, "score", MODEL, *files, "--jobs", "1")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0].startswith(f"accuracy {out['taught_accuracy']:.4f} ({out['taught_correct']} of 2 true slides of taught surfaces)"), lines
    assert (f"untaught surfaces: {out['untaught_unknown']} of their 2 slides called unknown ({out['untaught_unknown_share']:.4f}, the right "
            f"answer); open-set accuracy {out['open_set_accuracy']:.4f} ({out['open_set_correct']} of 4 true slides, one of an untaught "
            "surface right if called unknown)") in lines, lines
