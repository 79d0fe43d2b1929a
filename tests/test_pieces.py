"""A long slide is learnt by whole-slide candidates as its pieces too: what the pieces are, that they only ever train,
and how train and enrol take them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.learn.dataset import PIECE, PIECE_WINDOWS, LabelledSlide, SlideCounts, WindowSet, cut_long_slides
from tactiled.learn.enrol import enrol
from tactiled.learn.search import SPECTRUM
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here


def window_set(windows: list[int], copy: list[int] | None = None) -> WindowSet:
    """Slide k holds windows[k] windows of 0.25 s at 20 kHz, its rows in reverse time order; feature = the window's index
    within its slide (so a piece's mean says which windows it took) and the slide's number."""
    x, slide, spans = [], [], []
    for k, n in enumerate(windows):
        for i in reversed(range(n)):
            x.append([float(i), float(k)])
            slide.append(k)
            spans.append((i * 5000, (i + 1) * 5000))
    w = len(x)
    return WindowSet(np.array(x), np.array([f"S{k}" for k in slide], dtype=np.str_), np.array(slide, dtype=np.int64),
                     np.array(slide, dtype=np.int64), np.array(spans, dtype=np.int64), ["i", "k"], [f"f{k}" for k in range(len(windows))],
                     [], [None] * len(windows), SlideCounts(), {}, None if copy is None else np.array(copy, dtype=np.int8)[:w])


def test_a_long_slide_adds_its_pieces_as_training_rows_and_a_short_one_does_not() -> None:
    short, long = 2 * PIECE_WINDOWS - 1, 2 * PIECE_WINDOWS + 1
    means = window_set([short, long]).averaged()
    own = means.originals()
    # the slides as recorded: one row each, their windows' mean, as before
    assert own.tolist() == [True, True, False, False]
    assert np.allclose(means.x[own], [[(short - 1) / 2, 0], [(long - 1) / 2, 1]])
    assert np.array_equal(means.slide[own], [0, 1]) and means.copy is not None and set(means.copy[~own].tolist()) == {PIECE}
    # the long slide's pieces: its windows in time order, split in two runs of at least PIECE_WINDOWS
    first, second = np.arange(PIECE_WINDOWS + 1), np.arange(PIECE_WINDOWS + 1, long)
    assert np.allclose(means.x[~own], [[first.mean(), 1], [second.mean(), 1]])
    assert np.array_equal(means.spans[~own], [[0, len(first) * 5000], [len(first) * 5000, long * 5000]])
    assert means.y[~own].tolist() == ["S1", "S1"] and means.groups[~own].tolist() == [1, 1] and means.slide[~own].tolist() == [1, 1]
    # no slide long enough: the rows of before, and no copy numbers
    plain = window_set([short, short]).averaged()
    assert plain.copy is None and len(plain.y) == 2


def test_pieces_of_speed_copies_and_how_many() -> None:
    n = 3 * PIECE_WINDOWS + 2
    own = window_set([n])
    ws = window_set([2 * n])  # one slide: its windows as recorded, then as many of its copy's (feature 0 above 100)
    ws.x[:n], ws.spans[:n] = own.x, own.spans
    ws.x[n:], ws.spans[n:] = own.x + np.array([100.0, 0.0]), own.spans
    ws.copy = np.array([0] * n + [1] * n, dtype=np.int8)
    means = ws.averaged()
    assert means.copy is not None
    assert means.copy.tolist() == [0, 1] + [PIECE] * 6  # the slide, its copy, then three pieces of each
    assert means.originals().tolist() == [True] + [False] * 7
    pieces = means.x[2:, 0]
    assert np.all(pieces[:3] < 100) and np.all(pieces[3:] > 100)  # a piece never mixes a slide's windows with its copy's
    assert np.allclose(pieces[:3], [2.0, 7.0, 11.5])  # windows 0-4, 5-9 and 10-13 of 14, in time order


@pytest.fixture(scope="module")
def continuous(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three surfaces of the continuous scene: two recordings each, each one slide from its first sample to its last."""
    return write_dataset(tmp_path_factory.mktemp("pieces"), scene="continuous", seed=3, surfaces="3", files_per_surface=2)


def test_train_learns_long_slides_in_pieces_and_scores_them_whole(continuous: list[Path], tmp_path: Path) -> None:
    config = Config()
    said: list[str] = []
    res = train(continuous, config, candidates=[SPECTRUM], folds=2, group_by="file", progress=said.append)
    m = res.model
    told = [line for line in said if "pieces" in line]
    assert len(told) == 1 and "also learn the 6 slides of 8 windows or more as" in told[0], said  # train says what it did
    assert res.slides == 6 and res.oof is not None and res.oof[0].shape[0] == 6  # one out-of-fold score per slide
    assert m.novelty_x is not None and m.novelty_x.shape[0] == 6  # the unknown-surface test: the slides as recorded
    assert m.refit is not None and len(m.refit[1]) >= 6 * 3  # each slide of ~7 s also learnt as its pieces of ~1 s
    path = tmp_path / "m.npz"
    m.save(path)
    new = write_dataset(tmp_path / "new", scene="continuous", seed=4, surfaces="3", files_per_surface=1)[:2]  # recordings it has not learnt
    done = enrol(path, new, config, label="NEW", min_slides=2)
    assert done.added == {"NEW": 2}  # slides counted as recorded, learnt with their pieces
    assert done.model.refit is not None and list(done.model.refit[1]).count("NEW") >= 2 * 3


def test_cut_long_slides_cuts_a_long_slide_into_consecutive_even_slides_and_keeps_short_ones() -> None:
    long, short = LabelledSlide(0, 100, 190, "A", "label"), LabelledSlide(0, 500, 539, "B", "detected")  # 90 and 39 samples
    out = cut_long_slides([long, short], 20)
    assert out[-1] == short  # under twice the length: as it was
    cut = out[:-1]
    assert [(s.start, s.stop) for s in cut] == [(100, 122), (122, 145), (145, 167), (167, 190)]  # 4 of 22-23 samples, no gap
    assert all(s.label == "A" and s.source == "label" and s.file == 0 for s in cut)
    assert cut_long_slides([long], 45) == [LabelledSlide(0, 100, 145, "A", "label"), LabelledSlide(0, 145, 190, "A", "label")]
    assert cut_long_slides([long], 46) == [long]


def test_train_by_slide_cuts_one_long_recording_per_surface_into_slides_the_folds_can_split(continuous: list[Path], tmp_path: Path,
                                                                                             capfd: pytest.CaptureFixture[str]) -> None:
    """A lab whose data are one long slide per surface: train by file stops (naming --group-by slide); by slide it trains,
    saying how the slides were cut and that the estimate is optimistic, and the model labels a slide of another recording."""
    one = [p for p in continuous if p.name.endswith("_00.npz")]  # one recording of each of the three surfaces
    model = tmp_path / "m.npz"
    res = cli_here(capfd, "train", *map(str, one), "-o", str(model), "--method", "quick")
    assert res.returncode == 2 and not model.exists()
    assert "Ra" in res.stderr.strip().splitlines()[-1] and "--group-by slide" in res.stderr.strip().splitlines()[-1]
    res = cli_here(capfd, "train", *map(str, one), "-o", str(model), "--method", "quick", "--group-by", "slide")
    assert res.returncode == 0, res.stderr
    cut = [line for line in res.stderr.splitlines() if "are cut into slides of 2 to 4 s" in line]
    assert len(cut) == 1 and "the 3 slide(s) of 4 s or more" in cut[0] and "where 3 were found" in cut[0], res.stderr
    assert "optimistic" in res.stderr and "leaderboard (slide accuracy, grouped by slide:" in res.stdout
    other = [p for p in continuous if p.name.endswith("_01.npz")]
    res = cli_here(capfd, "replay", str(other[0]), "--model", str(model), "--json")
    assert res.returncode == 0, res.stderr
    finals = [m for m in map(json.loads, res.stdout.splitlines()) if m.get("final")]
    assert len(finals) == 1 and finals[0]["label"] is not None  # the whole recording is one slide, labelled
