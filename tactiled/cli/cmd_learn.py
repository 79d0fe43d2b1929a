"""``tactiled features``, ``train``, ``enrol``, ``score`` and ``evaluate``: learning from labelled recordings."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tactiled.cli import common as c
from tactiled.cli.common import EXIT_OK, EXIT_USAGE, Sub, command, config_of, files_done, say
from tactiled.errors import ModelError, TactiledError

if TYPE_CHECKING:
    from tactiled.files.recording import Recording

EXPERIMENTS = "abcdefg"


def experiments(text: str) -> str:
    """Experiment letters, each from :data:`EXPERIMENTS`."""
    unknown = sorted(set(text) - set(EXPERIMENTS))
    if unknown or not text:
        raise argparse.ArgumentTypeError(f"letters from {EXPERIMENTS} expected, got {text!r}")
    return text


experiments.__name__ = "experiment letters"


def cmd_features(args: argparse.Namespace) -> int:
    """Feature vectors of every window of every slide, into one .npz."""
    from tactiled.files.outputs import check_output
    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.feature_table import write_features

    config = config_of(args)
    check_output(args.output, args.force, (".npz",), args.files)  # before every window is analysed, not after
    recs = load_recordings(args.files, say)
    if not recs:
        raise TactiledError("no readable recordings")
    ws = write_features(args.output, recs, config, args.jobs, lambda m: print(f"features: {m}", file=sys.stderr, flush=True))
    print(f"{args.output}: {ws.x.shape[0]} windows of {len(ws.slides)} slides x {ws.x.shape[1]} features"
          + (f" (slides without a window: {ws.skipped})" if ws.skipped else ""))
    return EXIT_OK if len(recs) == len(args.files) else EXIT_USAGE


def interval_clause(band: list[float] | None, correct: int, n: int) -> str:
    """``, 95 % interval over recordings LOW-HIGH`` of score's headline (nothing without ``band``), saying where it comes from
    when every one of the ``n`` slides is right (or none is): no resample can vary then, and the rule of three gives it."""
    if not band:
        return ""
    rule = " (every slide right: the rule of three, 1 - 3/recordings)" if correct == n else \
        " (every slide wrong: the rule of three, 3/recordings)" if correct == 0 else ""
    return f", 95 % interval over recordings {band[0]:.4f}-{band[1]:.4f}{rule}"


def cmd_train(args: argparse.Namespace) -> int:
    """Search, fit and save a model; print the leaderboard and what calibration and novelty found."""
    from tactiled.files.outputs import check_output
    from tactiled.learn.train import train

    config = config_of(args)
    check_output(args.output, args.force, (".npz",), args.files)  # before minutes of search, not after
    result = train(args.files, config, method=args.method, folds=args.folds, seed=args.seed, min_slides=args.min_slides, drop_rare=args.drop_rare,
                   scheduler=args.scheduler, progress=lambda m: print(f"train: {m}", file=sys.stderr, flush=True), group_by=args.group_by,
                   novelty=args.novelty, ensemble=args.ensemble, speed=args.speed_copies, gain=args.gain_tolerance / 100,
                   **({} if args.untaught_share is None else {"untaught": args.untaught_share}))
    fingerprint = result.model.save(args.output)  # before any line: a closed stdout (train ... | head) loses no model
    print(f"leaderboard (slide accuracy, grouped by {args.group_by}: mean ± sd over folds; * the choice, the simplest within one standard error "
          "of the best" + (" and of the best of those under another gain" if args.gain_tolerance else "") + "):")
    width = max(len(row["candidate"]) for row in result.leaderboard)
    if args.gain_tolerance:
        g = 1 + args.gain_tolerance / 100
        print(f"  (beside each, its mean accuracy with every film's gain {g:g} or 1/{g:g} times what was recorded, together and in "
              "opposite directions, as another unit of the sensor can have; of the candidates within one standard error of the best, "
              "the choice is among those within one of the best of them there)")
    for row in result.leaderboard:
        mark = "*" if row.get("chosen") else " "
        gain = f"; {100 * row['gain_mean']:5.1f} % at another gain" if "gain_mean" in row else ""
        print(f"{mark} {row['candidate']:<{width}s} {100 * row['mean']:5.1f} ± {100 * row['sd']:4.1f} %{gain}")
        ens = row.get("ensemble")
        if ens:  # the chosen candidate with the spectral one (train --ensemble)
            what = "the model" if ens["used"] else "not used: more than one standard error below the chosen one"
            print(f"  {'+ ' + ens['partner']:<{width}s} {100 * ens['mean']:5.1f} ± {100 * ens['sd']:4.1f} % (the choice and it as an ensemble: {what})")
    recall_line(result.nested, result.per_class, args.group_by)
    cal, nov = result.model.summary.get("calibration", {}), result.model.summary.get("novelty", {})
    if cal:
        early = result.model.summary.get("early_calibration", {})
        print(f"confidence: calibrated ({cal['method']}) on {cal['slides']} out-of-fold slides"
              + (f"; provisional labels on {early['prefixes']} out-of-fold slide prefixes" if result.model.early_calibration else ""))
    if nov.get("known_rejected") is not None or nov.get("known_rejected_by"):
        ratio, far = nov.get("threshold") is not None, nov.get("distance_threshold") is not None
        if (ratio or far) and nov.get("known_rejected") is not None:
            known = (f"by leaving each recording out, {100 * nov['known_rejected']:.1f} % of the slides of a new recording of a known surface "
                     "slid as these were are called unknown (slid otherwise, more: by hand where these were by robot, or in strokes of "
                     "another length; a slide's speed moves its spectrum)" if nov.get("known_rejected_by") == "recording left out" else
                     f"by cross-validation, {100 * nov['known_rejected']:.1f} % of slides of known surfaces are called unknown")
            print(f"unknown surfaces: {known}, "
                  + (f"{100 * nov['unseen_flagged']:.1f} % of slides of a surface left out of training" if nov.get("unseen_flagged") is not None
                     else "and no surface could be left out to test it"))
        if nov.get("score") == "spectrum":
            print("unknown surfaces: " + ("a slide whose spectral shape is farther from every taught surface than 95 % of the slides of "
                                          "another recording of its own surface is called unknown" if far else
                                          "no slide will be called unknown (no surface has two recordings to set the threshold)"))
        elif nov.get("score") == "far":
            print("unknown surfaces: " + ("only a slide farther from every taught surface than they are from each other is called unknown "
                                          "(--novelty combined also tests for one between two taught surfaces)" if far else
                                          "no slide will be called unknown (fewer than two surfaces)"))
        elif not ratio:
            test = "distance" if nov.get("score") == "distance" else "distance-ratio"
            print(f"unknown surfaces: the {test} test flags nothing: by cross-validation, at --untaught-share {nov.get('untaught', 0.5):g} "
                  "it would cost more known slides than the untaught ones it catches are worth"
                  + ("; only a slide farther from every taught surface than they are from each other is called unknown" if far else
                     "; no slide will be called unknown"))
    print(f"{args.output}: {result.model.describe()}; fingerprint {fingerprint}")
    chosen = next((row for row in result.leaderboard if row.get("chosen")), {})
    print(another_unit(args.gain_tolerance, chosen.get("mean"), chosen.get("gain_mean"), result.model.partner is not None))
    return EXIT_OK


def recall_line(nested: dict[str, Any], per_class: dict[str, tuple[int, int, int]], group_by: str = "file") -> None:
    """Print the nested estimate per surface (its three lowest recalls) and its balanced accuracy, with a note when the
    surfaces' slide counts differ :data:`~tactiled.learn.search.IMBALANCE` times or more: the search then weighed each
    surface alike (``weighted``); else (``--method paper``) the estimate weighs each slide, so the larger surfaces count more."""
    from tactiled.learn.search import IMBALANCE

    recall = nested.get("recall") or {}
    if not recall:
        return
    low = sorted(recall.items(), key=lambda kv: (kv[1], kv[0]))[:3]
    unseen = "recordings" if group_by == "file" else "slides (of recordings it was fitted on: optimistic)"
    what = "the model" if nested.get("model") == "ensemble" else "the choice"
    print(f"nested CV per surface (recall of {what} on {unseen} it was not fitted on): lowest "
          + ", ".join(f"{k} {v:.2f}" for k, v in low) + f"; balanced accuracy {nested['balanced']:.3f} (each surface alike)")
    counts = [n for n, _, _ in per_class.values()]
    span = f"the surfaces have {min(counts)} to {max(counts)} slides" if counts else ""
    if nested.get("weighted"):
        print(f"{span}: the choice, its cross-validated accuracies and the nested estimate weigh each surface alike, as in use on "
              "surfaces met alike (and the svm and linear classifiers fit them so)")
    elif counts and min(counts) > 0 and max(counts) >= IMBALANCE * min(counts):
        print(f"{span}: the nested estimate weighs each slide, so the larger surfaces count more in it than in use on surfaces met "
              "alike; the balanced accuracy weighs each surface alike")


ANOTHER_UNIT = ("these estimates hold for new recordings with the sensor unit that made the training recordings: another unit (a swapped or "
                "re-glued fingertip) moves the films' resonances and gains, which can cost far more (in docs/evaluation.md, 25 to 40 points "
                "on neighbouring grades{measured}); check it with tactiled score on a few of its labelled recordings, and teach them with "
                "tactiled enrol")


def another_unit(tolerance: float, mean: float | None, under: float | None, ensemble: bool = False) -> str:
    """``train``'s last line: its estimates hold for the unit that recorded; with the choice's cross-validated accuracy
    ``mean`` as recorded and ``under`` the films' gains ``tolerance`` per cent off, what that costs it (``ensemble``: the
    model is the choice with its partner, and the figures are the choice's alone)."""
    whose = "the choice alone's (the model is it and its ensemble partner)" if ensemble else "the choice's"
    measured = (f"; here, with the films' gains {tolerance:g} % off, {whose} cross-validated accuracy is {100 * under:.1f} % against "
                f"{100 * mean:.1f} % as recorded" if mean is not None and under is not None else "")
    return ANOTHER_UNIT.format(measured=measured)


def cmd_enrol(args: argparse.Namespace) -> int:
    """Add a surface (or more slides of known ones) to a model; write a new model file, the input untouched."""
    from tactiled.files.outputs import check_output
    from tactiled.learn.enrol import enrol

    config = config_of(args)
    check_output(args.output, args.force, (".npz",), args.files)
    if args.model and Path(args.model).resolve() == Path(args.output).resolve():
        raise TactiledError(f"{args.output}: is the input model; enrol writes a new file and never changes its input")
    done = enrol(args.model or None, args.files, config, args.label, args.min_slides, say)
    for name, n in done.added.items():
        print(f"{name}: {n} slides{' (a new surface)' if name in done.new_classes else ' added to a known surface'}")
    fingerprint = done.model.save(args.output)
    print(f"{args.output}: {done.model.describe()}; fingerprint {fingerprint}")
    return EXIT_OK


def untaught_line(surface: str, slides: int, unknown: int, labelled: int) -> str:
    """score's line for a surface the model was not taught: how many of its slides came out unknown, labelled, or neither."""
    rest = [f"{labelled} labelled"] if labelled else []
    if slides - unknown - labelled > 0:
        rest.append(f"{slides - unknown - labelled} without a label for another reason")
    return (f"not a surface of the model: {surface}, {unknown} of its {slides} slides called unknown (the right answer)"
            + (f", {' and '.join(rest)}" if rest else ""))


def with_ground_truth(recs: list[tuple[str, Recording]]) -> list[tuple[str, Recording]]:
    """The recordings (name, recording) that carry ground truth (per-slide surfaces or a file label, which names the surface
    of each slide the detector finds: tactiled.learn.dataset); each other one is named in a line, skipped."""
    kept = []
    for name, rec in recs:
        if rec.slides() or rec.label is not None:
            kept.append((name, rec))
        else:
            say(f"skipped: {name}: no ground truth (neither per-slide surfaces nor a file label)")
    return kept


def cmd_score(args: argparse.Namespace) -> int:
    """Accuracy, coverage and calibration of a model over every true slide of held-out recordings."""
    from tactiled.learn.dataset import check_distinct, load_recordings, some_names
    from tactiled.learn.model import load_model
    from tactiled.learn.score import score_recordings

    config = config_of(args)
    model = load_model(args.model)
    recs = []  # as replay: a recording of another rate or channel count than the model is its line, and the others go on
    for name, rec in load_recordings(args.files, say):
        try:
            model.check_stream(rec.fs, rec.channels, "it")
        except ModelError as exc:
            say(f"skipped: {name}: {exc}")  # the file skipped first, as for an unreadable one
            continue
        recs.append((name, rec))
    scored = with_ground_truth(recs)
    if not recs:
        raise TactiledError(f"no recording to score: none is readable and of {args.model}'s rate and channels (listed above)")
    if not scored:
        raise TactiledError("no recording with ground truth (per-slide surfaces or a file label) to score")
    # as train: one recording given twice (or a copy of it) would count its slides twice; one with per-slide truth is refused
    # before the replays, one with a file label alone once they found its slides (two files of silence count nothing)
    twice = "its slides would count twice in the accuracy"
    check_distinct([(n, r) for n, r in scored if r.slides()], twice)
    report = score_recordings(scored, config, model, args.jobs, files_done("score"))
    if report["n"] == 0:  # only file labels, and the detector found no slide in any of them: an accuracy of 0 of 0 is no score
        shown = some_names([n for n, _ in scored])
        raise TactiledError(f"no true slide to score: the detector found no slide in {shown} (a file label names the surface of "
                            "each slide the detector finds; see `tactiled replay` on one of them)")
    check_distinct([rec for rec, f in zip(scored, report["files"], strict=True) if f["slides"]], twice)
    if args.json:
        print(json.dumps(report))
        return EXIT_OK if len(scored) == len(args.files) else EXIT_USAGE
    within = interval_clause(report["taught_interval95"], report["taught_correct"], report["taught_n"])
    headline = (f"accuracy {report['taught_accuracy']:.4f} ({report['taught_correct']} of {report['taught_n']} true slides of taught "
                f"surfaces{within})" if report["taught_n"] else "accuracy: no true slide of a surface the model was taught")
    print(f"{headline}; coverage {report['coverage']:.4f} ({report['labelled']} of {report['n']} true slides labelled); "
          + (f"accuracy of the labelled {report['accuracy_of_labelled']:.4f}" if report["labelled"] else "no slide labelled"))
    if report["abstained"]:
        print("no label: " + ", ".join(f"{k} {v}" for k, v in sorted(report["abstained"].items())))
    print(f"unknown surfaces: {report['unknown']} of {report['n']} true slides")
    for surface, (slides, unknown) in report["untaught"].items():
        print(untaught_line(surface, slides, unknown, report["untaught_labelled"].get(surface, 0)))
    if report["untaught_n"]:
        print(f"untaught surfaces: {report['untaught_unknown']} of their {report['untaught_n']} slides called unknown "
              f"({report['untaught_unknown_share']:.4f}, the right answer); open-set accuracy {report['open_set_accuracy']:.4f} "
              f"({report['open_set_correct']} of {report['n']} true slides, one of an untaught surface right if called unknown)")
    if report["ece"] is not None:
        null = report["ece_calibrated"]
        print(f"confidence: expected calibration error {report['ece']:.3f} over the {report['calibration_slides']} slides of taught surfaces "
              f"(10 bins; a perfectly calibrated model would show {null[0]:.3f}, up to {null[1]:.3f} in 95 % of draws, on as many slides), "
              f"Brier score {report['brier']:.3f}")
    elif report["untaught"]:
        print("confidence: no slide of a taught surface to measure its calibration on (it is the probability of a right label on one)")
    if report["unpaired_detections"]:
        print(f"detections outside any true slide: {report['unpaired_detections']}")
    taught = {cls: r for cls, r in report["recall"].items() if cls not in report["untaught"]}  # the untaught have their lines above
    width = max((len(cls) for cls in taught), default=0)  # names longer than 12 characters kept the column, shifted
    for cls, r in taught.items():
        print(f"  {cls:>{max(12, width)}s}: recall {r:.3f}")
    return EXIT_OK if len(scored) == len(args.files) else EXIT_USAGE  # the files skipped (unreadable, no ground truth) were named


def cmd_evaluate(args: argparse.Namespace) -> int:
    """The papers' experiments into a report folder."""
    from tactiled.files.outputs import check_folder
    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.evaluate import run_evaluation
    from tactiled.learn.train import check_recordings

    config = config_of(args)
    check_folder(args.report, args.force)  # before minutes of experiments, not after
    recs = with_ground_truth(load_recordings(args.files, say))
    if len(recs) < 2:
        raise TactiledError("evaluation needs at least two readable recordings with ground truth (per-slide surfaces or a file label)")
    check_recordings(recs, len(recs))  # one rate and channel count, no recording twice
    results = run_evaluation(recs, config, Path(args.report), experiments=args.experiments, folds=args.folds, quick=args.quick, seed=args.seed,
                             progress=lambda m: print(f"evaluate: {m}", file=sys.stderr, flush=True))
    print(f"{Path(args.report) / 'report.md'}: {len(recs)} recordings, {results['seconds']:.0f} s")
    return EXIT_OK if len(recs) == len(args.files) else EXIT_USAGE  # as features and score: the skipped files were named


def add_commands(sub: Sub) -> None:
    """features, train, evaluate, enrol, score."""
    p = command(sub, "features", "feature vectors of every slide", cmd_features, "tactiled features data/sim/*.npz -o features.npz")
    p.add_argument("files", nargs="+", help="recordings (.npz) whose slides to analyse")
    p.add_argument("-o", "--output", required=True, help="features file to write (.npz: one row per window, docs/features.md)")
    p.add_argument("--force", action="store_true", help=c.FORCE_HELP)
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--jobs", type=c.jobs, default=0, metavar="N", help=c.JOBS_HELP)

    p = command(sub, "train", "train a model from labelled recordings (finds what works on them)", cmd_train,
                "tactiled train data/sim/*.npz -o my_model.npz")
    p.add_argument("files", nargs="+", help="labelled recordings (.npz): per-slide ground truth or a file-level label")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    p.add_argument("--force", action="store_true", help=c.FORCE_HELP)
    p.add_argument("--config", help="config file (detector, spikes, feature settings; default: the built-in defaults)")
    p.add_argument("--method", choices=("auto", "quick", "paper"), default="auto",
                   help="auto: score features, classifiers and windows by grouped CV and keep the simplest within one standard error of "
                        "the best; quick: a small search for a first model in "
                        "seconds (band energies and texture, linear and kNN); paper: the papers' DWT + SFS + ELM")
    p.add_argument("--folds", type=c.int_in(2, 1000), default=5,
                   help="outer cross-validation folds, grouped by file (at most the files of the surface with fewest)")
    p.add_argument("--min-slides", type=c.count, default=2, help="fewest slides a surface needs")
    p.add_argument("--drop-rare", action="store_true", help="train without surfaces that have too few slides instead of stopping")
    p.add_argument("--group-by", choices=("file", "slide"), default="file",
                   help="what cross-validation folds keep together: file (every surface needs two recordings) or slide "
                        "(allows one recording per surface, and cuts a slide of 4 s or more into slides of 2 to 4 s, so that a "
                        "recording that is one long slide can be cross-validated; the estimates are then optimistic, and train says so)")
    p.add_argument("--scheduler", help="dask.distributed scheduler address (tcp://host:port) to run the cross-validation on a cluster "
                                        "(default: this machine, every core); checked before any recording is read")
    p.add_argument("--seed", type=c.seed, default=0, help=c.SEED_HELP + " (the same files, options and seed give the same model file)")
    p.add_argument("--novelty", choices=("spectrum", "far", "combined", "ratio", "distance"), default="spectrum",
                   help="how a slide is judged unlike every taught surface (label null, reason unknown_surface): spectrum (the default), "
                        "the distance from the shape of its spectrum (per film, log band powers less their mean) to the nearest taught "
                        "surface, beyond what 95 %% of slides of another recording of a known surface reach (computed whatever the "
                        "classifier reads); the others measure the classifier's own features: far, "
                        "its distance to the nearest surface beyond the step between taught surfaces (keeps labelling on another "
                        "unit of the sensor or a new sheet of a known grade); combined, that or its distance to the nearest surface "
                        "over that to the next, where cross-validation says it pays (also flags an untaught surface between two "
                        "taught ones, and slides of another unit that a shift puts there: docs/evaluation.md); ratio, that ratio "
                        "alone; distance, its distance to the nearest training slides (flags more untaught surfaces between "
                        "taught grades, but also most slides of another unit)")
    p.add_argument("--untaught-share", type=c.number_in(0.01, 0.99, "share"), default=None,
                   help="with --novelty combined, ratio or distance (spectrum and far have no threshold to weigh): the share of slides you expect "
                        "on surfaces the model is not taught; the threshold calls known slides unknown (at most 5 %% of them by "
                        "cross-validation) only where the untaught slides it catches are worth it at this share; 0.5 weighs a caught "
                        "untaught slide and a rejected known one alike (default: 0.1)")
    p.add_argument("--gain-tolerance", type=c.number_in(0, 100, "per cent"), default=20.0,
                   help="how far each film's gain may lie from the recording unit's on another unit of the sensor (a swapped or "
                        "re-glued fingertip, another amplifier): every candidate is also scored on its held-out slides with every "
                        "film's gain that many per cent higher or lower (together, and in opposite directions), and of the "
                        "candidates within one standard error of the "
                        "best, those within one standard error of the best of them under that gain go on to the simplest, so that "
                        "a model that tells surfaces apart by one film's level alone is not chosen when one as accurate holds; 0: "
                        "as recorded only (default: %(default)g)")
    p.add_argument("--speed-copies", type=c.number_in(0, 30, "per cent"), default=0.0,
                   help="also learn from two copies of each training slide resampled as if slid this many per cent slower and "
                        "faster (its spectrum that much lower and higher), e.g. 5; copies are never scored, and the unknown-surface "
                        "test and calibration read the slides as recorded; about twice the training time; never with --method "
                        "paper. Measured: whole-slide spectral candidates gain on new recordings, the default's choice does not "
                        "(docs/evaluation.md) (default: 0, none)")
    p.add_argument("--ensemble", choices=("off", "always", "guarded"), default="off",
                   help="whether the chosen candidate and the plain spectral one (spectrum / svm / 0.25 s / slide mean) make one model, "
                        "the normalised product of their probabilities, when the chosen one's windows are the spectral one's "
                        "(0.25 s from the start): off, always, or guarded (only when its cross-validated accuracy is within one "
                        "standard error of the chosen one's); default off; never with --method quick or paper")

    p = command(sub, "evaluate", "the papers' experiments by grouped cross-validation", cmd_evaluate,
                "tactiled evaluate data/sim/*.npz --report report/")
    p.add_argument("files", nargs="+", help="recordings (.npz) with per-slide ground truth or a file-level label (its slides found by the "
                   "detector, as train), all of one rate and channel count, at least two surfaces and two recordings of each (folds "
                   "are grouped by recording)")
    p.add_argument("--report", required=True, help="output folder: report.md, report.json, PNG figures")
    p.add_argument("--force", action="store_true", help="write into a report folder that is not empty")
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--experiments", type=experiments, default=EXPERIMENTS,
                   help="which experiments, as letters (e.g. ag): a: classifiers, b: window grid, c: sampling rate, d: feature count, "
                        "e: clustering, f: error against run time, g: the default method against decision time")
    p.add_argument("--folds", type=c.int_in(2, 1000), default=5, help="cross-validation folds, grouped by file (at most the files of the surface with fewest)")
    p.add_argument("--quick", action="store_true", help="small grids and fewer features (for tests)")
    p.add_argument("--seed", type=c.seed, default=0, help=c.SEED_HELP)

    p = command(sub, "enrol", "teach a trained model a new surface from a few slides (no new search)", cmd_enrol,
                "tactiled enrol my_model.npz new_surface/*.npz --label P60 -o my_model2.npz")
    p.add_argument("model", help="model file (.npz) to start from; it is never changed ('' for the shipped model)")
    p.add_argument("files", nargs="+", help="recordings (.npz) of the surface; every slide in them is enrolled")
    p.add_argument("--label", help="the surface's name for every slide of the files (default: the recordings' own labels, "
                                   "e.g. recordings of known surfaces made with another unit of the sensor)")
    p.add_argument("-o", "--output", required=True, help="new model file to write (.npz)")
    p.add_argument("--force", action="store_true", help=c.FORCE_HELP)
    p.add_argument("--min-slides", type=c.count, default=5, help="fewest usable slides a surface needs (default 5)")
    p.add_argument("--config", help=c.CONFIG_HELP)

    p = command(sub, "score", "accuracy of a model on ground-truth slides", cmd_score, "tactiled score my_model.npz held_out/*.npz")
    p.add_argument("model", help="model file (.npz) to score")
    p.add_argument("files", nargs="+", help="recordings (.npz) with per-slide ground truth or a file label, unseen in training; "
                   "each once (two files with the same samples, e.g. a copy, are refused)")
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--json", action="store_true", help="the report as one JSON object. The headline accuracy (taught_accuracy) is over the "
                   "slides of surfaces the model was taught, an unknown or no label wrong; the slides of untaught surfaces are "
                   "scored apart (untaught_unknown_share: the share called unknown, their right answer), and open_set_accuracy "
                   "counts every slide, an untaught one right if called unknown; accuracy: right labels over every slide")
    p.add_argument("--jobs", type=c.jobs, default=0, metavar="N", help=c.JOBS_HELP)
