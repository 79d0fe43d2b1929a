"""train's "% of slides of a surface left out of training called unknown": each surface left out of everything the
unknown-surface test is fitted on, the standardisation of the spectral shapes included."""

from __future__ import annotations

import copy

import numpy as np

from tactiled.learn.model import Model, default_model_path, load_model, novelty_parts, over_thresholds
from tactiled.learn.search import fit_model_novelty, left_out_flagged


def _taught_without(model: Model, rows: np.ndarray, labels: np.ndarray, groups: np.ndarray, surface: str) -> np.ndarray:
    """Whether a model whose unknown-surface test was fitted without ``surface`` calls each of its slides unknown, as the
    daemon's :meth:`Model.novelty_many` decides it."""
    rest = labels != surface
    taught = copy.copy(model)
    fit_model_novelty(taught, rows[rest], labels[rest], groups[rest], "spectrum")
    z = taught.novelty_standardise(rows[~rest])
    parts = novelty_parts(z, taught.novelty_x, taught.novelty_y, taught.novelty_k, taught.novelty_score, alone=True,
                          scale=taught.novelty_surface_scale)
    flagged: np.ndarray = over_thresholds(parts, taught.novelty_threshold, taught.novelty_distance_threshold) > 1.0
    return flagged


def test_the_left_out_figure_is_what_a_model_taught_without_the_surface_does_with_its_slides() -> None:
    model = load_model(default_model_path())
    width = model.novelty_x.shape[1]
    rng = np.random.default_rng(5)
    # 6 surfaces of 4 recordings of 3 slides, five of them overlapping, the sixth like them but for one band 100 standard
    # deviations off (a grating's line): taught, that band's spread over all slides would hide how far off it is
    which = np.repeat(np.arange(6), 12)
    rows = 0.5 * rng.standard_normal((6, width))[which] + rng.standard_normal((72, width))
    rows[which == 5, 0] += 100.0
    labels, groups = np.array([f"s{i}" for i in which]), np.repeat(np.arange(24), 3)
    fit_model_novelty(taught := copy.copy(model), rows, labels, groups, "spectrum")
    figure = taught.summary["novelty"]["unseen_flagged"]
    assert taught.summary["novelty"]["unseen_flagged_by"] == "surface left out"
    flagged = {s: _taught_without(model, rows, labels, groups, s) for s in np.unique(labels)}
    assert flagged["s5"].all()  # the surface with the line, left out, is unknown on every slide
    through_models = np.concatenate(list(flagged.values())).mean()
    assert abs(figure - through_models) <= 1.0 / len(rows) + 1e-12  # the same slides, to a distance's rounding
    assert figure < 0.5  # the overlapping surfaces, left out, are not told from their neighbours


def test_the_left_out_figure_is_none_when_nothing_can_be_left_out_and_finite_on_constant_shapes() -> None:
    rows = np.zeros((12, 4))
    assert left_out_flagged(rows, np.array(["a"] * 12), np.repeat(np.arange(4), 3), 3) is None  # one surface
    assert left_out_flagged(rows, np.repeat(np.array(["a", "b"]), 6), np.repeat(np.arange(2), 6), 3) is None  # one recording each
    figure = left_out_flagged(rows, np.repeat(np.array(["a", "b", "c"]), 4), np.repeat(np.arange(6), 2), 3)  # every shape the same
    assert figure == 0.0
