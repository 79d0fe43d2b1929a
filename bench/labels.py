"""Labels a robot can act on, per simulator scene: accuracy against a plain spectral baseline, on the same unit and on others.

For each scene: a training set (unit 0), a same-unit test set (other tracks of the same specimens) and one
other-unit test set per ``--other-units`` (another unit of the sensor, new specimens of the same grades;
docs/simulator.md; two units, because one draw of the tolerances says little).
Trains the default (``tactiled train``) and the papers' method (``--method paper``), and the plain
whole-slide spectral classifier described below on the true slides; scores each end to end on both test
sets (the daemon's pipeline, every true slide counted), with the calibration error (ECE, 10 equal-width
bins) and Brier score of the confidence, the unknown-surface rate on known surfaces, and the provisional
labels (time from slide start to the first one the final label confirmed; how often one was wrong). Every
candidate of the default search is refitted and scored on the same-unit test, beside its cross-validated
accuracy. The default model also meets the 15 gratings of the other surface family (``<scene>,grating``, same
kinematics and fingertip, 1 file x 3 slides each, seed 400; far from every grade): how many of their 45 slides come
out unknown (``--no-gratings`` skips it). Then three of the fifteen surfaces are left out of training: how many of
their test slides come out unknown, and how many of the known ones, on the same unit and on the other units (with
``--mixed``, of the far-apart set).

The plain baseline, outside tactiled's code: for each true slide, the Welch PSD of each channel over the
whole slide (segments of 1024 samples at 20 kHz, scaled to the rate), the log energy in 24 log-spaced bands
from 20 Hz to 0.45 fs, the log spectral centroid and the kurtosis; StandardScaler; RBF SVM (C=10).

Usage: python bench/labels.py [--scenes "hand;robot;..."] [--files 3] [--test-files 2] [--slides 3] [--out DIR] [--json FILE]
       [--other-units 1,2] [--no-paper] [--leave-out-scenes "hand;robot;one-channel"] [--novelty far|combined|ratio|distance]
       [--no-gratings] [--ensemble off|always|guarded] [--candidates-on-units] [--mixed] [--speed-copies PCT]

``--mixed``: each scene's surfaces are 8 grades spread over the range and 7 gratings (:func:`dataset`), far apart as most
labs' sets are, instead of 15 neighbouring grades; the far-surface test (the gratings) is then left out.

``--ensemble`` trains every default model with ``train --ensemble``; where the model is an ensemble, the winner alone (the
candidate ``train`` chose, with its own calibration) is scored on the same test sets beside it, and a second table gives
both, gated (unknowns wrong) and top class, with the ensemble's and the winner's cross-validated accuracy.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal, stats
from scratch import scratch

from tactiled.config import Config
from tactiled.files.recording import Recording
from tactiled.learn.dataset import load_recordings
from tactiled.learn.score import calibration_scores, score
from tactiled.learn.train import train
from tactiled.run.replay import by_slide, pair_results, replay_recording
from tactiled.sim.simulate import write_dataset

DEFAULT = "hand;robot;continuous;fluctuating;hot-gain;one-channel;grating;continuous,one-channel;fluctuating,one-channel;hand,hot-gain"
LEAVE_OUT = (2, 7, 12)  # of the 15 surfaces, in Ra order: three inside the range, none at its ends


def ra(surface: str) -> float:
    """The grade's Ra of a surface name (``Ra0.61`` -> 0.61): the order LEAVE_OUT counts in."""
    return float("".join(c for c in surface if c.isdigit() or c == "."))


MIXED = (8, 7)  # --mixed: grades spread over the range (39 % apart in Ra), and gratings


def dataset(out: Path, spec: str, seed: int, files: int, slides: int, mixed: bool = False, **kw: Any) -> list[Path]:
    """Recordings of the 15 surfaces of scene ``spec`` (write_dataset); ``mixed``: of 8 grades spread over the range and 7
    gratings instead, far apart as a lab's sandpapers, fabrics and machined textures are (the gratings' file names carry
    ``+grating``)."""
    if not mixed:
        return write_dataset(out, scene=spec, seed=seed, files_per_surface=files, slides_per_file=slides, **kw)
    return (write_dataset(out, scene=spec, seed=seed, surfaces=str(MIXED[0]), files_per_surface=files, slides_per_file=slides, **kw)
            + write_dataset(out, scene=f"{spec},grating", seed=seed + 1, surfaces=str(MIXED[1]), files_per_surface=files,
                            slides_per_file=slides, **kw))


def plain_features(x: np.ndarray, fs: float) -> list[float]:
    """The plain baseline's features of one slide (n, C): per channel 24 log band energies, log centroid, kurtosis."""
    nper = max(64, round(1024 * fs / 20000))
    out: list[float] = []
    edges = np.geomspace(20.0, 0.45 * fs, 25)
    for c in range(x.shape[1]):
        f, p = signal.welch(x[:, c], fs=fs, nperseg=min(nper, len(x)))
        out += [float(np.log(p[(f >= a) & (f < b)].sum() + 1e-20)) for a, b in itertools.pairwise(edges)]
        out += [float(np.log((f * p).sum() / (p.sum() + 1e-30) + 1e-9)), float(np.nan_to_num(stats.kurtosis(x[:, c])))]
    return out


def plain_rows(recs: list[tuple[str, Recording]]) -> tuple[np.ndarray, np.ndarray]:
    """(features, labels) of every true slide of ``recs``."""
    rows, labels = [], []
    for _, rec in recs:
        volts = rec.samples.astype(np.float64) * rec.volts_per_count
        for a, b, surface in rec.slides():
            rows.append(plain_features(volts[a:b], rec.fs))
            labels.append(surface)
    return np.array(rows), np.array(labels)


def plain_baseline(train_recs: list[tuple[str, Recording]], tests: dict[str, list[tuple[str, Recording]]]) -> dict[str, float]:
    """The plain whole-slide spectral classifier's accuracy on each test set."""
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    x, y = plain_rows(train_recs)
    clf = make_pipeline(StandardScaler(), SVC(C=10.0)).fit(x, y)
    out = {}
    for name, recs in tests.items():
        xt, yt = plain_rows(recs)
        out[name] = float(np.mean(clf.predict(xt) == yt))
    return out


def end_to_end(recs: list[tuple[str, Recording]], config: Config, model: Any) -> dict[str, Any]:
    """Scores (accuracy, coverage, ECE, Brier, unknowns) and provisional-label timing over every true slide of ``recs``."""
    results = [replay_recording(rec, config, model) for _, rec in recs]
    sc = score(recs, results, model.classes)
    first_right, provisional, wrong = [], 0, 0
    conf, hit = [], []
    for (_, rec), res in zip(recs, results, strict=True):
        truth, paired, _ = pair_results(rec, res)
        early = {r.slide_id: ps for r, ps in by_slide(res)}
        for t, r in zip(truth, paired, strict=True):
            if r is None:
                continue
            ps = early.get(r.slide_id, [])
            provisional += len(ps)
            wrong += sum(p.label != t for p in ps)
            conf += [p.confidence for p in ps]
            hit += [p.label == t for p in ps]
            confirmed = [p.used_s for p in ps if r.label is not None and p.label == r.label]
            if confirmed:
                first_right.append(confirmed[0])
    return {"accuracy": sc["accuracy"], "top_accuracy": sc["top_accuracy"], "coverage": sc["coverage"], "n": sc["n"], "ece": sc["ece"],
            "ece_calibrated": sc["ece_calibrated"], "brier": sc["brier"],
            "unknown": sc["unknown"], "abstained": sc["abstained"], "reliability": sc["reliability"],
            "provisional": {"slides_with_confirmed": len(first_right), "median_s": float(np.median(first_right)) if first_right else None,
                            "p90_s": float(np.percentile(first_right, 90)) if first_right else None, "labels": provisional,
                            "wrong": wrong / provisional if provisional else None,
                            "ece": calibration_scores(np.array(conf, dtype=np.float64), np.array(hit, dtype=bool))["ece"]}}


def unknown_share(recs: list[tuple[str, Recording]], config: Config, model: Any) -> tuple[int, int]:
    """(true slides of ``recs`` that come out unknown, true slides), end to end."""
    flagged = total = 0
    for _, rec in recs:
        truth, paired, _ = pair_results(rec, replay_recording(rec, config, model))
        flagged += sum(r is not None and r.reason == "unknown_surface" for r in paired)
        total += len(truth)
    return flagged, total


def leave_out(spec: str, tr: list[Path], test: list[tuple[str, Recording]], config: Config, opts: dict[str, Any] | None = None,
              others: dict[int, list[tuple[str, Recording]]] | None = None) -> dict[str, Any]:
    """Train on 12 of 15 surfaces (``opts``: train's options); the unknown rate on test slides of the 3 left out and of the 12
    known, on the same unit and on each of ``others`` (unit: its test recordings)."""
    surfaces = sorted({s for _, r in test for _, _, s in r.slides()}, key=ra)
    gone = {surfaces[i] for i in LEAVE_OUT if i < len(surfaces)}
    keep = [p for p in tr if not any(f"_{g}_" in p.name for g in gone)]
    res = train(keep, config, progress=lambda m: None, **(opts or {}))
    shares = left_out_share(test, config, res.model, gone)
    return {"scene": spec, "left_out": sorted(gone), "unseen_unknown": shares["unseen"], "known_unknown": shares["known"],
            "unseen_slides": shares["unseen_slides"], "known_slides": shares["known_slides"], "cv_estimate": res.model.summary.get("novelty"),
            "units": {u: left_out_share(recs, config, res.model, gone) for u, recs in (others or {}).items()}}


def left_out_share(recs: list[tuple[str, Recording]], config: Config, model: Any, gone: set[str]) -> dict[str, float]:
    """Of the true slides of ``recs``, end to end: the share of those of the surfaces ``gone`` (left out of training) and of
    the known ones that come out unknown, and how many of each there are."""
    flagged = {True: [0, 0], False: [0, 0]}
    for _, rec in recs:
        truth, paired, _ = pair_results(rec, replay_recording(rec, config, model))
        for t, r in zip(truth, paired, strict=True):
            flagged[t in gone][0] += r is not None and r.reason == "unknown_surface"
            flagged[t in gone][1] += 1
    return {"unseen": flagged[True][0] / max(1, flagged[True][1]), "known": flagged[False][0] / max(1, flagged[False][1]),
            "unseen_slides": flagged[True][1], "known_slides": flagged[False][1]}


def table_row(out: dict[str, Any], units: list[int]) -> str:
    """One scene's row of the table in docs/evaluation.md."""
    s, o, pl, pp, prov = out["same"], out["other"], out["plain"], out.get("paper"), out["same"]["provisional"]

    def each(f: Any) -> str:
        return " / ".join(f(u) for u in units)

    return (f"| {out['scene']} | {100 * out['nested_cv']:.1f} % | **{100 * s['accuracy']:.1f} %** ({100 * s['top_accuracy']:.1f}) | "
            + each(lambda u: f"**{100 * o[u]['accuracy']:.1f}** ({100 * o[u]['top_accuracy']:.1f})") + " % | "
            f"{100 * pl['same']:.1f} / " + each(lambda u: f"{100 * pl[f'other{u}']:.1f}") + " % | "
            + (f"{100 * pp['same']:.1f} / " + each(lambda u: f"{100 * pp[f'other{u}']:.1f}") + " % | " if pp else "- | ")
            + f"{s['ece']:.3f} / " + each(lambda u: f"{o[u]['ece']:.3f}") + f" | {s['ece_calibrated'][0]:.3f} / {s['ece_calibrated'][1]:.3f} "
            + f"| {s['brier']:.3f} | {100 * s['unknown'] / s['n']:.1f} / "
            + each(lambda u: f"{100 * o[u]['unknown'] / o[u]['n']:.1f}") + " % | "
            + (f"{prov['median_s']:.2f} / {prov['p90_s']:.2f}, {100 * prov['wrong']:.0f} %, ECE {prov['ece']:.3f} |"
               if prov["median_s"] is not None else "none |")
            + f" {out['train_s']:.0f} |")


def ensemble_row(out: dict[str, Any], units: list[int]) -> str:
    """One scene's row of the ensemble table: CV of the ensemble and the winner, then each model's gated and top-class accuracy."""
    e = out["ensemble"]

    def accs(res: dict[str, Any]) -> str:
        return " / ".join(f"{100 * res[k]['accuracy']:.1f} ({100 * res[k]['top_accuracy']:.1f})" for k in ["same", *[f"other{u}" for u in units]])

    cv = f"{100 * e['mean']:.1f} / {100 * e['chosen_cv']:.1f} %" + ("" if e.get("within_one_se", True) else " (beyond 1 SE)") if "mean" in e else "-"
    mine = {"same": out["same"], **{f"other{u}": out["other"][u] for u in units}}
    return (f"| {out['scene']} | {out['winner']} | {cv} | {accs(mine) if out['ensemble']['is_ensemble'] else '(not an ensemble)'} % | "
            + (f"{accs(out['alone'])} % |" if "alone" in out else f"{accs(mine)} % |"))


def candidates_table(rows: list[dict[str, Any]], units: list[int]) -> str:
    """Each candidate's means over the scenes (distinct data: ``hot-gain`` and ``hand,hot-gain`` once): cross-validated and
    same-unit top class, top class per other unit, and over the other units top class and accuracy with unknowns counted
    wrong; then the plain baseline's and the chosen candidate's (``--candidates-on-units``)."""
    seen, distinct = set(), []
    for r in rows:
        key = frozenset(r["scene"].split(",")) - {"hand"} if "hot-gain" in r["scene"] else r["scene"]
        if key not in seen:
            seen.add(key)
            distinct.append(r)
    names = sorted({c["candidate"] for r in distinct for c in r["candidates"]})
    head = ("| candidate | scenes | CV | same unit | " + " | ".join(f"unit {u}" for u in units)
            + " | other units, top class | other units, unknowns wrong |\n|---|---|---|---|" + "---|" * len(units) + "---|---|")
    lines = [head]

    def line(name: str, n: int, cv: str, same: float, per: list[float], gated: float | None) -> str:
        g = f"{100 * gated:.1f}" if gated is not None else "-"
        return (f"| {name} | {n} | {cv} | {100 * same:.1f} | " + " | ".join(f"{100 * v:.1f}" for v in per)
                + f" | {100 * float(np.mean(per)):.1f} | {g} |")

    for name in names:
        cs = [c for r in distinct for c in r["candidates"] if c["candidate"] == name]
        per = [float(np.mean([c["other"][u][1] for c in cs])) for u in units]
        gated = float(np.mean([c["other"][u][0] for c in cs for u in units]))
        lines.append(line(name, len(cs), f"{100 * np.mean([c['cv'] for c in cs]):.1f}", float(np.mean([c["same_top"] for c in cs])), per, gated))
    plain = [float(np.mean([r["plain"][f"other{u}"] for r in distinct])) for u in units]
    lines.append(line("plain baseline", len(distinct), "-", float(np.mean([r["plain"]["same"] for r in distinct])), plain, None))
    won = [next(c for c in r["candidates"] if c["candidate"] == r["winner"]) for r in distinct]
    lines.append(line("the chosen candidate", len(won), f"{100 * np.mean([c['cv'] for c in won]):.1f}", float(np.mean([c["same_top"] for c in won])),
                      [float(np.mean([c["other"][u][1] for c in won])) for u in units], float(np.mean([c["other"][u][0] for c in won for u in units]))))
    return "\n".join(lines)


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=DEFAULT, help="scene specs separated by ';'")
    ap.add_argument("--files", type=int, default=3, help="training files per surface")
    ap.add_argument("--test-files", type=int, default=2, help="test files per surface, per test set")
    ap.add_argument("--slides", type=int, default=3, help="slides per file")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--other-units", default="1,2", help="the other units of the sensor to test on, each with its own new specimens")
    ap.add_argument("--no-paper", action="store_true", help="skip the papers' method (its forward selection takes minutes)")
    ap.add_argument("--leave-out-scenes", default="hand;robot;one-channel", help="scenes for the unknown-surface test ('' for none)")
    ap.add_argument("--novelty", default=None, help="train --novelty for every model (default: train's)")
    ap.add_argument("--no-gratings", action="store_true", help="skip the far-surface test (the default model on the 15 gratings)")
    ap.add_argument("--ensemble", default=None, help="train --ensemble for the default models (default: train's)")
    ap.add_argument("--candidates-on-units", action="store_true", help="also score every candidate on every other unit, and print a "
                    "table of each candidate's means over the scenes")
    ap.add_argument("--mixed", action="store_true", help="each scene's surfaces are 8 grades spread over the range and 7 gratings (far "
                    "apart, as most labs' sets are) instead of 15 neighbouring grades; no far-surface test")
    ap.add_argument("--speed-copies", type=float, default=None, help="train --speed-copies for every model (default: train's)")
    args = ap.parse_args()
    opts: dict[str, Any] = {"novelty": args.novelty} if args.novelty else {}
    if args.speed_copies is not None:
        opts["speed"] = args.speed_copies
    ens_opts: dict[str, Any] = {"ensemble": args.ensemble} if args.ensemble else {}
    config = Config()
    units = [int(u) for u in args.other_units.split(",") if u]
    root = scratch(args.out, "tactiled-labels-")
    rows: list[dict[str, Any]] = []
    print("| scene | nested CV | default: same unit (top class) | other units (top class, unknowns included) | plain baseline: same / other units "
          "| papers' method: same / other units | ECE same / other units | a calibrated model's ECE, same unit: median / 95 % "
          "| Brier same | unknown on known (same / other units) | provisional: median / p90 s, wrong, ECE | train s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for spec in [s for s in args.scenes.split(";") if s]:
        name = spec.replace(",", "+")
        tr = dataset(root / name / "train", spec, 100, args.files, args.slides, args.mixed)
        same = load_recordings(dataset(root / name / "same", spec, 200, args.test_files, args.slides, args.mixed))
        others = {u: load_recordings(dataset(root / name / f"other{u}", spec, 200 + 100 * u, args.test_files, args.slides, args.mixed,
                                             unit=u, specimen=u)) for u in units}
        train_recs = load_recordings(tr)
        out: dict[str, Any] = {"scene": spec, "plain": plain_baseline(train_recs, {"same": same, **{f"other{u}": r for u, r in others.items()}})}
        t0 = time.perf_counter()
        res = train(tr, config, progress=lambda m: None, keep_models=True, **opts, **ens_opts)
        out["train_s"] = time.perf_counter() - t0
        out["winner"], out["nested_cv"] = res.winner, res.nested["mean"]
        out["same"], out["other"] = end_to_end(same, config, res.model), {u: end_to_end(r, config, res.model) for u, r in others.items()}
        chosen = next(r for r in res.leaderboard if r["candidate"] == res.winner)
        out["ensemble"] = {**chosen.get("ensemble", {}), "chosen_cv": chosen["mean"], "chosen_sd": chosen["sd"],
                           "is_ensemble": res.model.partner is not None}
        scored = {r["candidate"]: end_to_end(same, config, res.models[r["candidate"]]) for r in res.leaderboard}
        if res.model.partner is not None:  # the winner alone, as train --ensemble off would have made it (scored above on the same unit)
            alone = res.models[res.winner]
            out["alone"] = {"same": scored[res.winner], **{f"other{u}": end_to_end(r, config, alone) for u, r in others.items()}}
        out["candidates"] = [{"candidate": r["candidate"], "cv": r["mean"], "same": scored[r["candidate"]]["accuracy"],
                              "same_top": scored[r["candidate"]]["top_accuracy"]} for r in res.leaderboard]
        if args.candidates_on_units:  # every candidate on every other unit too: (accuracy, top class) per unit
            for c in out["candidates"]:
                c["other"] = {u: [e["accuracy"], e["top_accuracy"]] for u, r in others.items()
                              for e in [end_to_end(r, config, res.models[c["candidate"]])]}
        if not args.no_paper:
            pres = train(tr, config, method="paper", progress=lambda m: None, **opts)
            out["paper"] = {"same": end_to_end(same, config, pres.model)["accuracy"], "nested_cv": pres.nested["mean"],
                            **{f"other{u}": end_to_end(r, config, pres.model)["accuracy"] for u, r in others.items()}}
        if not args.no_gratings and not args.mixed and "grating" not in spec:
            far = load_recordings(write_dataset(root / name / "gratings", scene=f"{spec},grating", seed=400, files_per_surface=1,
                                                slides_per_file=3))
            out["gratings_unknown"], out["gratings_slides"] = unknown_share(far, config, res.model)
        rows.append(out)
        print(table_row(out, units), flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps({"scenes": rows}, indent=1, default=float))
    if any("alone" in r for r in rows):
        print("\n| scene | winner | CV: ensemble / winner alone | ensemble: same / " + " / ".join(f"unit {u}" for u in units)
              + " (top class) | winner alone: same / " + " / ".join(f"unit {u}" for u in units) + " (top class) |")
        print("|---|---|---|---|---|")
        for r in rows:
            print(ensemble_row(r, units))
    if args.candidates_on_units:
        print(candidates_table(rows, units))
    # cross-validation scores the top class (no novelty gate): against the test's top class
    gaps = [(r["scene"], c["candidate"], c["cv"] - c["same_top"]) for r in rows for c in r["candidates"]]
    worst = max(gaps, key=lambda g: abs(g[2])) if gaps else None
    for r in rows:
        over = [c for c in r["candidates"] if abs(c["cv"] - c["same_top"]) > 0.10]
        print(f"{r['scene']}: {len(r['candidates']) - len(over)} of {len(r['candidates'])} candidates' CV within 10 points of their test "
              "accuracy (top class)" + "".join(f"; {c['candidate']} {100 * (c['cv'] - c['same_top']):+.1f}" for c in over), file=sys.stderr)
    for r in rows:
        if "gratings_unknown" in r:
            print(f"gratings ({r['scene']}, far from every grade): {r['gratings_unknown']} of their {r['gratings_slides']} slides unknown", flush=True)
    print("\nlargest gap between a candidate's cross-validated and same-unit test accuracy (top class): "
          + (f"{100 * worst[2]:+.1f} points ({worst[1]} on {worst[0]})" if worst else "-"), file=sys.stderr)
    leave = []
    for spec in [s for s in args.leave_out_scenes.split(";") if s]:
        name = "leave-" + spec.replace(",", "+")
        tr = dataset(root / name / "train", spec, 100, args.files, args.slides, args.mixed)
        test = load_recordings(dataset(root / name / "test", spec, 200, args.test_files, args.slides, args.mixed))
        others = {u: load_recordings(dataset(root / name / f"unit{u}", spec, 200 + 100 * u, args.test_files, args.slides, args.mixed,
                                             unit=u, specimen=u)) for u in units}
        leave.append(leave_out(spec, tr, test, config, opts, others))
        lo = leave[-1]
        print(f"leave out {', '.join(lo['left_out'])} ({spec}): {100 * lo['unseen_unknown']:.1f} % of their {lo['unseen_slides']} slides unknown, "
              f"{100 * lo['known_unknown']:.1f} % of {lo['known_slides']} known ones"
              + "".join(f"; unit {u}: {100 * o['unseen']:.1f} % / {100 * o['known']:.1f} %" for u, o in lo["units"].items()), flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps({"scenes": rows, "leave_out": leave}, indent=1, default=float))


if __name__ == "__main__":
    main()
