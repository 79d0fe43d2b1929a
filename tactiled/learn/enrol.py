"""``tactiled enrol``: teach a trained model one more surface (or more slides of surfaces it knows) in seconds.

The search is not run again: the model keeps its features, windows, classifier and parameters. Its file keeps the
standardised rows its classifier was fitted on (format 4), so enrolment maps them back to raw features, adds the
new slides' rows (analysed exactly as the daemon analyses them), and fits the same classifier on the union; the
novelty data gets the new slides and its threshold is fitted again by the same grouped rule as in training (a spectrum
test keeps its provisional labels' thresholds as the same multiples of the new one). The
confidence keeps the original model's calibration (fitted on its out-of-fold scores; enrolment has none of its own).
An ensemble (format 7) refits both members on the new slides, each on its own columns of the one analysis and with
its own fusion; the members' and the ensemble's temperatures are kept with the calibration.

A surface needs at least :data:`MIN_SLIDES` usable slides. Without a ``label`` the recordings' own labels are used:
that is how recordings of known surfaces made with *another unit* of the sensor are added, after a fingertip swap.

A recording the model already learnt (trained or enrolled before) is refused, as ``train`` refuses two files of the same
samples: its slides would sit at distance 0 from "another recording" and shrink the unknown-surface threshold (an audit's
model of 8 grades enrolled with its own 24 training files: 88 -> 66 of 96 new slides right, 23 called unknown). The model
file keeps no digest of its recordings, but it keeps every learnt slide's novelty row (format 4 on, all enrol accepts):
a slide whose row equals one of them, to rounding (:data:`SAME_SLIDE`), is one it learnt. File names are not compared:
two recordings of different days may share one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.core.pipeline import start_level
from tactiled.errors import ModelError, TactiledError
from tactiled.files.recording import case_twins, check_label_option, surface_name
from tactiled.learn.dataset import (
    Progress,
    WindowSet,
    check_distinct,
    collect_windows,
    find_slides,
    load_recordings,
    some_names,
    speed_ratios,
    undetected,
    undetected_text,
)
from tactiled.learn.model import MAX_CLASSES, FloatArray, Model, fit_pipeline, load_model, take_columns
from tactiled.learn.search import NOVELTY_TESTS, PARAMS, fit_model_novelty, reasons_text

MIN_SLIDES = 5
SAME_SLIDE = 1e-6  # standardised novelty units: a learnt slide analysed again differs by 0 to 4e-16; another recording's by > 0.5


@dataclass
class Enrolled:
    """What :func:`enrol` made: the new model (not yet saved), the usable slides added per surface, and the files."""

    model: Model
    added: dict[str, int]
    files: list[str]
    new_classes: list[str]


def enrol(model_path: str | Path | None, paths: Sequence[str | Path], config: Config, label: str | None = None,
          min_slides: int = MIN_SLIDES, progress: Progress | None = None) -> Enrolled:
    """Add the slides of the recordings ``paths`` to the model at ``model_path`` (None: the shipped one), each labelled
    ``label`` (None: the recordings' own labels). Raises :class:`TactiledError` (one line) when the model keeps no
    training rows, a recording does not fit the model, or a surface has fewer than ``min_slides`` usable slides."""
    say = progress or (lambda m: None)
    old = load_model(model_path)
    where = model_path or "the shipped model"
    if old.refit is None or old.novelty_x is None or old.novelty_y is None or old.novelty_groups is None:
        raise ModelError(f"{where}: an older model file keeps no training rows; retrain it with this tactiled to enrol into it")
    check_label_option(label)  # the rule a recording's label follows (docs/recordings.md)
    score, untaught, enrolled = _summary_read(old, where)
    recs = load_recordings(paths, say)
    if len(recs) != len(paths):
        raise TactiledError(f"{len(paths) - len(recs)} of {len(paths)} recordings unreadable (named above); nothing enrolled")
    for name, rec in recs:
        old.check_stream(rec.fs, rec.channels, name, where)
    check_distinct(recs, "its slides would count twice")
    per_file, counts = find_slides(recs, config)  # as train found its slides (what the learnt-recordings check compares)
    level = start_level(old, config.detector)
    if level is not None:  # the daemon running the model, with its start level, finds no slide in a recording of rest; the
        # detector without it, undecided, takes such a recording for one slide from the first sample to the last
        # (only the recordings that could be such: slides found, no per-slide truth; the others are not detected again)
        doubtful = [(name, rec) for (name, rec), slides in zip(recs, per_file, strict=True) if slides and not rec.slides()]
        live, _ = find_slides(doubtful, config, level)
        rest = [name for (name, _), seen in zip(doubtful, live, strict=True) if not seen]
        if rest:
            raise TactiledError(f"no slide to enrol in {some_names(rest)}: the daemon running {where} finds none there (at rest, by the "
                                "level it learnt between slides; recordings of the surface being slid over, please); nothing enrolled")
    if label is not None:  # as a recording's names are read (NFC)
        per_file = [[replace(s, label=surface_name(label)) for s in slides] for slides in per_file]
    silent = undetected(per_file, [r.fs for _, r in recs], config.detector.min_slide_s)
    if silent:  # they would widen what the unknown-surface test measures against, for every surface
        raise TactiledError(undetected_text(silent) + "; nothing enrolled")
    # the classifier learns the new slides as train did: with their speed-perturbed copies, if it learnt from copies
    try:
        speeds = speed_ratios(float(old.summary.get("speed_copies", 0.0)))
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{where}: summary speed_copies: {exc}") from None
    ws = collect_windows(recs, config, old.settings, found=(per_file, counts), speeds=speeds)
    slides = ws.averaged()  # one row per slide with a usable window (and per copy of it)
    learnt = learnt_recordings(old, slides)
    if learnt:
        n, m = (sum(v[i] for v in learnt.values()) for i in (0, 1))
        raise TactiledError(f"{', '.join(recs[g][0] for g in learnt)}: {where} already learnt {n} of their {m} slides (the same samples, trained "
                            "or enrolled before): enrolled again they would count twice and shrink its unknown-surface threshold; give only "
                            "recordings it has not learnt")
    labelled = (slides.y != "") & slides.originals()
    table = ws.per_class()  # {surface: (slides, slides with a usable window, files)}, a surface none of whose slides is usable too
    if not table and (label is not None or any(r.label is not None or r.slides() for _, r in recs)):
        raise TactiledError(f"no slide to enrol: the detector found none in {some_names([n for n, _ in recs])} (recordings of the "
                            "surface being slid over; see tactiled replay on one of them)")
    if not table:
        raise TactiledError("the recordings carry no labels (per-slide ground truth or a file label): pass --label NAME")
    known = {k.casefold(): k for k in old.classes}
    twins = [(k, known[k.casefold()]) for k in table if k not in old.classes and k.casefold() in known]
    if twins:  # before any other check of the new slides: the name is what to mend first
        raise TactiledError("; ".join(f"{k}: {where} knows {m}, which differs only in case" for k, m in twins)
                            + ": enrolled, it would be a new surface; give the name the model knows (--label) to teach it more of that one")
    alike = case_twins(k for k in table if k not in old.classes)
    if alike:
        raise TactiledError("; ".join(" and ".join(g) for g in alike) + ": new surfaces whose names differ only in case would be "
                            "taught as different surfaces; give each surface one name")
    short = [f"{k} ({ok})" if ok == n else f"{k} ({ok} of {n} slides usable)" for k, (n, ok, _) in table.items() if ok < min_slides]
    if short:
        why = f" (slides without a usable window: {reasons_text(ws.skipped)})" if ws.skipped else ""
        raise TactiledError(f"too few usable slides for {', '.join(short)}: enrolment needs at least {min_slides} per surface{why}; record more")
    added = {k: ok for k, (_, ok, _) in table.items()}
    grown = len(set(old.classes) | set(added))
    if grown > MAX_CLASSES:  # a file its own loader would refuse
        raise TactiledError(f"enrolment would give the model {grown} classes, more than the {MAX_CLASSES} a model file may hold; nothing written")
    pipe, refit, params = _grown(old, slides if old.settings.fusion == "features" else ws, old.names)
    files = [Path(n).name for n, _ in recs]
    record = {"from": old.fingerprint, "slides": added, "files": files}
    summary: dict[str, Any] = {**old.summary, "enrolled": [*enrolled, record]}
    new = replace(old, params=params, classes=[str(k) for k in pipe[-1].classes_], pipeline=pipe, summary=summary, fingerprint="", refit=refit)
    if old.partner is not None:  # an ensemble: its second member learns the same slides (its own columns and fusion)
        p = old.partner
        p_pipe, p_refit, p_params = _grown(p, slides if p.settings.fusion == "features" else ws, old.names)
        new.partner = replace(p, params=p_params, classes=new.classes, pipeline=p_pipe, refit=p_refit)
    rows = np.vstack([old.novelty_unstandardise(old.novelty_x), new.novelty_features(slides.x[labelled])])
    groups = np.concatenate([old.novelty_groups, slides.groups[labelled] + int(old.novelty_groups.max(initial=-1)) + 1])
    labels = np.concatenate([old.novelty_y, slides.y[labelled]]).astype(np.str_)
    new.novelty_k, new.early_calibration = old.novelty_k, old.early_calibration
    fit_model_novelty(new, rows, labels, groups, score, untaught)
    return Enrolled(new, added, files, [k for k in added if k not in old.classes])


def _summary_read(model: Model, where: str | Path) -> tuple[str, float, list[Any]]:
    """What enrolment reads of ``model``'s training summary, checked (one line naming the file and key; the loader checks only
    what every command reads): the unknown-surface test and the share of untaught slides it was trained with (the summary
    says "far" or "spectrum" where the model file says "combined" without a ratio threshold; a model from before the share:
    Youden's J, 0.5), and the earlier enrolments' records."""
    trained = model.summary.get("novelty", {})
    if not isinstance(trained, dict):
        raise ModelError(f"{where}: header.summary.novelty: must be an object")
    score, untaught = trained.get("score", model.novelty_score), trained.get("untaught", 0.5)
    if score not in NOVELTY_TESTS:
        raise ModelError(f"{where}: header.summary.novelty.score: must be one of {', '.join(NOVELTY_TESTS)}")
    if not (isinstance(untaught, (int, float)) and not isinstance(untaught, bool) and 0.0 < untaught < 1.0):
        raise ModelError(f"{where}: header.summary.novelty.untaught: must be a number in (0, 1)")
    enrolled = model.summary.get("enrolled", [])
    if not isinstance(enrolled, list):
        raise ModelError(f"{where}: header.summary.enrolled: must be a list of the earlier enrolments")
    return str(score), float(untaught), enrolled


def learnt_recordings(model: Model, slides: WindowSet) -> dict[int, tuple[int, int]]:
    """{recording: (slides the model already learnt, its slides)} of the recordings (``slides.groups``) of which ``model``
    learnt a slide: one whose novelty row (:meth:`~tactiled.learn.model.Model.novelty_features` of its mean raw features,
    standardised as the model's) is within :data:`SAME_SLIDE` of one of ``model.novelty_x`` (n, F''), in every column.
    ``slides``: one row per slide (:meth:`WindowSet.averaged`; speed copies are not compared). Empty when none."""
    if model.novelty_x is None or not len(model.novelty_x):
        return {}
    keep = slides.originals()
    z = model.novelty_standardise(model.novelty_features(slides.x[keep]))
    same = np.array([bool(np.abs(model.novelty_x - row).max(axis=1).min() <= SAME_SLIDE) for row in z], dtype=bool)
    groups = slides.groups[keep]
    return {int(g): (int(same[groups == g].sum()), int(np.count_nonzero(groups == g))) for g in np.unique(groups[same])}


def _grown(member: Model, rows: WindowSet, names: tuple[str, ...]) -> tuple[Any, tuple[FloatArray, npt.NDArray[np.str_]], dict[str, Any]]:
    """(pipeline, standardised training rows, parameters) of ``member``'s classifier fitted again, with the same classifier and
    parameters, on its training rows and the labelled rows of ``rows`` (one per window, or per slide for a whole-slide member;
    raw features of the analysis, columns ``names``, of which it reads its own); a kNN keeps as many neighbours as the search
    asks for, unless the rarest surface has fewer rows."""
    if member.refit is None:
        raise ModelError("a model member keeps no training rows; retrain it with this tactiled to enrol into it")
    keep = rows.y != ""
    x = np.vstack([member.unstandardise(member.refit[0]), take_columns(rows.x[keep], names, member.inputs)])
    y = np.concatenate([np.asarray(member.refit[1], dtype=np.str_), rows.y[keep]])
    params = dict(member.params)
    if member.kind == "knn":
        params["n_neighbors"] = max(int(params.get("n_neighbors", 1)), int(PARAMS["knn"]["n_neighbors"]))
    pipe, refit = fit_pipeline(x, y, member.inputs, member.kind, params, member.seed)
    if member.kind == "knn":
        params["n_neighbors"] = int(pipe[-1].n_neighbors)
    return pipe, refit, params
