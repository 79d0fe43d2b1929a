"""``tactiled train``: recordings → slides (the daemon's detector, paired with ground truth) → model search → model file.

:func:`train` is the whole command as a library call. Training never drops a surface
silently: the slides of every surface are counted first (a surface named by file labels in whose files the detector
found no slide counts 0, and each such file is named), and a surface with fewer than
``min_slides`` is an error naming it (``drop_rare`` proceeds without it, saying so). Once the
windows are analysed, the same rules hold for the slides with a usable window (a slide too
short or too damaged for any window teaches nothing): a surface with too few of them is an error
naming it and why (``drop_rare``: left out, said, and listed in the summary's ``dropped``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from tactiled.config import Config
from tactiled.core.detect import front_end_settings
from tactiled.errors import TactiledError
from tactiled.files.recording import Recording, case_twins
from tactiled.learn.dataset import (
    CROSS_VALIDATION,
    GROUP_PIECE_S,
    LabelledSlide,
    Progress,
    SlideCounts,
    check_distinct,
    cut_long_slides,
    find_slides,
    load_recordings,
    undetected,
    undetected_text,
)
from tactiled.learn.levels import learn_start_level
from tactiled.learn.search import (
    ENSEMBLE_DEFAULT,
    ENSEMBLE_MODES,
    GAIN_DEFAULT,
    NOVELTY_DEFAULT,
    NOVELTY_TESTS,
    SPEED_DEFAULT,
    UNTAUGHT_SHARE,
    Candidate,
    SearchResult,
    UsableTable,
    check_scheduler,
    gain_option,
    paper,
    quick_candidates,
    reasons_text,
    search,
    speed_option,
)

METHODS = ("auto", "quick", "paper")
GROUP_BY = ("file", "slide")


def check_recordings(recs: Sequence[tuple[str, Recording]], wanted: int, why: str = CROSS_VALIDATION) -> None:
    """Every file readable, one rate and channel count, no recording twice (:func:`check_distinct`, ``why``)."""
    if len(recs) != wanted:
        raise TactiledError("unreadable recordings (listed above); nothing written")
    if not recs:
        raise TactiledError("no recordings given")
    kinds: dict[tuple[float, int], str] = {}  # (fs, channels) -> the first file of that kind
    for path, r in recs:
        kinds.setdefault((r.fs, r.channels), path)
    if len(kinds) > 1:
        which = "; ".join(f"{path}: {fs:g} Hz, {c} channel{'s' if c > 1 else ''}" for (fs, c), path in kinds.items())
        raise TactiledError(f"recordings differ in fs or channels ({which}); use one rate and channel count at a time")
    check_distinct(recs, why)


def file_labels(recs: Sequence[tuple[str, Recording]], per_file: list[list[LabelledSlide]], say: Progress) -> list[str | None]:
    """The file-level label of each recording (None where per-slide truth gives the slides), saying each labelled file the
    detector found no slide in (its surface may still have slides from other files: said, not lost silently), and each
    recording with neither a label nor per-slide truth (a ``record`` without ``--label``: its slides teach no surface)."""
    labels = [None if rec.slides() else rec.label for _, rec in recs]
    for (name, rec), label, slides in zip(recs, labels, per_file, strict=True):
        if label is not None and not slides:
            say(f"no slide detected in {name} (label {label})")
        elif label is None and not rec.slides():
            say(f"{name}: no label and no per-slide truth (recorded without --label?): its {len(slides)} slide(s) teach no surface")
    return labels


def class_table(per_file: list[list[LabelledSlide]], labels: Sequence[str | None] = ()) -> dict[str, tuple[int, int, int]]:
    """{surface: (slides, slides the detector found, files with a slide of it)}. ``labels``: the file-level labels of the
    recordings; a surface they name without a slide is a row of zeros, so that it meets the slide rules (it was left out of
    the table, and of the model, without a word)."""
    out: dict[str, list[Any]] = {label: [0, 0, set()] for label in labels if label is not None}
    for slides in per_file:
        for s in slides:
            if s.label is None:
                continue
            row = out.setdefault(s.label, [0, 0, set()])
            row[0] += 1
            row[1] += s.source != "truth"
            row[2].add(s.file)
    return {k: (v[0], v[1], len(v[2])) for k, v in sorted(out.items())}


def check_two_recordings(table: dict[str, tuple[int, int, int]], hint: str = "", what: str = "slides") -> None:
    """Refuse (one line naming them) surfaces of :func:`class_table` with a single recording: cross-validation grouped by
    recording can never test them on one it did not train on (every such slide would count as wrong). ``hint``: what
    else the command allows, appended to the advice; ``what``: the slides counted (``usable slides``)."""
    single = [k for k, (_, _, files) in table.items() if files < 2]
    if single:
        raise TactiledError(f"surface(s) {', '.join(single)} have a single recording with {what}: cross-validation grouped by recording cannot "
                            f"test them on a recording it did not train on; record a second file of each{hint}")


def usable_check(min_slides: int, drop_rare: bool, group_by: str, say: Progress, dropped: list[str]) -> Callable[[UsableTable], list[str]]:
    """The ``check_usable`` of :func:`~tactiled.learn.search.search`: the rules of the slide table (at least ``min_slides``;
    under ``group_by`` file, two recordings) on the slides with a usable window. A surface short of usable slides is an
    error naming it, how many of its slides are usable and why the others are not, or, with ``drop_rare``, one to train
    without (said, and appended to ``dropped``); a single recording with usable slides is refused as :func:`check_two_recordings`."""

    def check(table: UsableTable) -> list[str]:
        def told(k: str) -> str:
            n, ok, _, why = table[k]
            return f"{k}: {ok} of {n} slides usable" + (f" ({reasons_text(why)})" if why else "")

        for k, (n, ok, _, _) in table.items():
            if ok < n:
                say(f"  {told(k)}")
        short = [k for k, (_, ok, _, _) in table.items() if ok < min_slides]
        if short and not drop_rare:
            raise TactiledError(f"too few slides with a usable window (< {min_slides}): {'; '.join(told(k) for k in short)}; "
                                "record more (or longer) slides, or pass --drop-rare to train without them")
        if short:
            say(f"training without {', '.join(short)} (--drop-rare): too few slides with a usable window")
            dropped.extend(short)
        if group_by == "file":
            check_two_recordings({k: (ok, 0, files) for k, (_, ok, files, _) in table.items() if k not in short},
                                 ", or pass --group-by slide (an optimistic estimate)", "usable slides")
        else:  # folds by slide: a surface of one slide is never tested on a slide it did not learn from
            single = [k for k, (_, ok, _, _) in table.items() if k not in short and ok < 2]
            if single:
                raise TactiledError(f"surface(s) {', '.join(single)} have a single usable slide: cross-validation grouped by slide "
                                    "cannot test them on a slide it did not train on; record more slides of each")
        return short

    return check


def train(paths: Sequence[str | Path], config: Config, *, method: str = "auto", folds: int = 5, seed: int = 0, min_slides: int = 2,
          drop_rare: bool = False, scheduler: str | None = None, progress: Progress | None = None,
          candidates: Sequence[Candidate] | None = None, keep_models: bool = False, group_by: str = "file",
          novelty: str = NOVELTY_DEFAULT, ensemble: str = ENSEMBLE_DEFAULT, untaught: float = UNTAUGHT_SHARE,
          speed: float = SPEED_DEFAULT, gain: float = GAIN_DEFAULT) -> SearchResult:
    """Train a model on labelled recordings; returns the search result (its ``model`` is ready to save).

    ``candidates`` narrows the default search (``method="auto"``) to the given ones; ``keep_models``: see
    :func:`search`. ``group_by``: ``file`` (folds never split a recording; every surface needs two) or ``slide``
    (allowed with one recording per surface, with a warning that the estimates are optimistic; a slide of
    2·:data:`GROUP_PIECE_S` or more is cut into slides of :func:`cut_long_slides`, so a recording that is one long slide
    gives the folds several). ``novelty``: the unknown-surface tests (:data:`~tactiled.learn.search.NOVELTY_TESTS`):
    ``spectrum``, the default, flags a slide whose spectral shape is farther from every taught surface than another
    recording of a taught surface is; ``far`` flags a slide farther from every taught surface than they are from one
    another; ``combined`` adds the distance ratio, which flags a slide between two taught surfaces where
    cross-validation says that pays, and also slides of another unit of the sensor that a shift puts there; ``ratio`` is
    that test alone; ``distance`` flags slides far from the nearest training slides (more untaught surfaces between
    taught grades, but also most slides of another unit or a new sheet of a known one). ``untaught``: the share of
    slides expected on surfaces the model was not taught, in (0, 1); with ``combined``, ``ratio`` and ``distance``,
    their threshold rejects known slides only where that catches enough untaught ones at this share
    (:func:`~tactiled.learn.search.novelty_threshold`). ``ensemble`` (:data:`~tactiled.learn.search.ENSEMBLE_MODES`):
    whether the winner of the search and the plain spectral candidate make one model
    (:func:`~tactiled.learn.search.search`); ``quick`` and ``paper`` never do (their search has no spectral candidate).
    ``speed``: per cent slower and faster of the two speed-perturbed copies of each training slide the search also
    learns from (0: none; ``paper`` never). ``gain``: each film's gain tolerance the choice also weighs (``train
    --gain-tolerance``, :func:`~tactiled.learn.search.search`; ``paper`` never).
    """
    say = progress or (lambda m: None)
    if method not in METHODS:
        raise TactiledError(f"--method: must be one of {', '.join(METHODS)}, got {method!r}")
    if folds < 2:
        raise TactiledError(f"--folds: must be >= 2, got {folds}")
    if min_slides < 1:
        raise TactiledError(f"--min-slides: must be >= 1, got {min_slides}")
    if group_by not in GROUP_BY:
        raise TactiledError(f"--group-by: must be one of {', '.join(GROUP_BY)}, got {group_by!r}")
    if seed < 0:
        raise TactiledError(f"--seed: must be >= 0, got {seed}")
    if novelty not in NOVELTY_TESTS:
        raise TactiledError(f"--novelty: must be one of {', '.join(NOVELTY_TESTS)}, got {novelty!r}")
    if not 0.0 < untaught < 1.0:
        raise TactiledError(f"--untaught-share: must be in (0, 1), got {untaught}")
    if ensemble not in ENSEMBLE_MODES:
        raise TactiledError(f"--ensemble: must be one of {', '.join(ENSEMBLE_MODES)}, got {ensemble!r}")
    speed_option(speed)  # before the recordings load
    if method == "paper" and speed:
        raise TactiledError("--speed-copies: not with --method paper (its forward selection over the copies would take several times "
                            "as long); leave one of them out")
    gain_option(gain)
    if scheduler is not None:  # "" too: an empty address is a mistake, not a request for the local cores
        check_scheduler(scheduler)  # likewise: a refused address is said at once, not after the analysis
    recs = load_recordings(paths, say)
    check_recordings(recs, len(paths))
    per_file, counts = find_slides(recs, config)
    spans = [[(s.start, s.stop) for s in slides] for slides in per_file]  # every slide found, for the detector's start level
    surfaces = [[s.label for s in slides] for slides in per_file]  # theirs (file labels are given below, by file_labels)
    say(f"{len(recs)} files, {sum(len(s) for s in per_file)} slides ({counts.truth} in ground truth, {counts.detected} detected, "
        f"{sum(counts.missed.values())} missed by the detector, {sum(counts.false.values())} detections outside any true slide)")
    for name, n in counts.missed.items():
        say(f"  detector missed {n} true slide(s) in {name}: used at their true bounds")
    labels = file_labels(recs, per_file, say)
    if group_by == "slide":  # a recording that is one long slide gives cross-validation several groups
        length = round(GROUP_PIECE_S * recs[0][1].fs)
        cut = [cut_long_slides(slides, length) for slides in per_file]
        n_long = sum(s.stop - s.start >= 2 * length for slides in per_file for s in slides)
        if n_long:
            say(f"--group-by slide: the {n_long} slide(s) of {2 * GROUP_PIECE_S:g} s or more are cut into slides of {GROUP_PIECE_S:g} "
                f"to {2 * GROUP_PIECE_S:g} s ({sum(map(len, cut))} slides where {sum(map(len, per_file))} were found), so that a "
                "recording that is one long slide gives the folds several")
        per_file = cut
    silent = undetected(per_file, [r.fs for _, r in recs], config.detector.min_slide_s)
    if silent and not drop_rare:
        raise TactiledError(undetected_text(silent) + "; check the recordings, or pass --drop-rare to train without them")
    if silent:
        say(f"training without {', '.join(silent)} (--drop-rare): " + undetected_text(silent))
        per_file = [[s for s in slides if s.label not in silent] for slides in per_file]
    table = class_table(per_file, labels)
    say("slides per surface (slides, found by the detector, files):")
    for label, (n, det, files) in table.items():
        say(f"  {label}: {n}, {det}, {files}")
    for twins in case_twins(table):
        say(f"warning: surfaces {' and '.join(twins)} differ only in case: taught as {len(twins)} surfaces; if they are one, give "
            "their recordings one name (docs/recordings.md)")
    if not table:
        raise TactiledError("no labelled slides: the recordings carry neither per-slide ground truth nor a file label "
                            "(tactiled record --label SURFACE, or docs/recordings.md)")
    rare = [k for k, (n, _, _) in table.items() if n < min_slides]
    named = ", ".join(f"{k} ({table[k][0]} slide{'' if table[k][0] == 1 else 's'})" for k in rare)
    if rare and not drop_rare:
        raise TactiledError(f"too few slides (< {min_slides}) for surface(s) {named}; record more, or pass --drop-rare to train without them"
                            + (f" (or --group-by slide, if each is one slide of {2 * GROUP_PIECE_S:g} s or more)"
                               if group_by == "file" and any(table[k][0] for k in rare) else ""))
    if rare:
        say(f"training without {named} (--drop-rare)")
        per_file = [[s for s in slides if s.label not in rare] for slides in per_file]
    if group_by == "file":
        check_two_recordings({k: v for k, v in table.items() if k not in rare}, ", or pass --group-by slide (an optimistic estimate)")
    if group_by == "slide":
        say("warning: --group-by slide: folds split recordings, so slides of one recording are both trained and tested on; "
            "the cross-validated accuracy, the calibration and the novelty threshold are optimistic")
        serial = iter(range(sum(len(s) for s in per_file)))
        per_file = [[replace(s, file=next(serial)) for s in slides] for slides in per_file]
    found: tuple[list[list[LabelledSlide]], SlideCounts] = (per_file, counts)
    unusable: list[str] = []  # surfaces --drop-rare left out for too few slides with a usable window
    check = usable_check(min_slides, drop_rare, group_by, say, unusable)
    if method == "paper":
        result = paper(recs, config, folds=folds, seed=seed, progress=say, scheduler=scheduler, found=found, novelty=novelty,
                       untaught=untaught, check_usable=check, group_by=group_by, gain=gain)
    else:
        if method == "quick" and candidates is None:
            candidates = quick_candidates()
        result = search(recs, config, folds=folds, seed=seed, progress=say, scheduler=scheduler, found=found, candidates=candidates,
                        keep_models=keep_models, novelty=novelty, ensemble=ensemble, untaught=untaught, speed=speed,
                        check_usable=check, group_by=group_by, gain=gain)
    result.model.start_level, note = learn_start_level([r for _, r in recs], spans, config.detector, surfaces)
    result.model.start_front = front_end_settings(config.detector) if result.model.start_level is not None else None
    say(note)
    result.model.summary["files_trained"] = [Path(n).name for n, _ in recs]
    result.model.summary["dropped"] = sorted([*rare, *unusable, *silent])
    return result
