"""What the distance-ratio unknown-surface test buys and costs, per scene: the same model with and without it.

For each scene, a model trained with ``tactiled train --novelty combined`` (its other options the defaults) on 15
surfaces recorded with unit 0 (3 files x 3 slides each, seed 100, as bench/labels.py) is replayed end to end, every true
slide counted and an unknown counted wrong, as trained ("on": the ratio test where cross-validation found it pays, and
the far-surface distance test) and with its ratio threshold removed ("off": the far test alone, which is what
``train --novelty far``, the default, writes), on:

- the same unit (2 files x 3 slides per surface, seed 200) and units 1-4 with new specimens (seeds 300-600): accuracy,
  and how many known slides come out unknown;
- the 15 gratings of the other surface family (``<scene>,grating``, 1 file x 3 slides each, seed 400; not with
  ``--mixed`` or a grating scene): how many come out unknown;
- three of the fifteen surfaces left out of training (bench/labels.py's LEAVE_OUT), on the same unit and units 1 and 2:
  how many of their slides come out unknown, and of the known ones.

``--mixed``: each scene's surfaces are 8 grades spread over the range and 7 gratings (bench/labels.py --mixed).

Usage: python bench/ratio_test.py [--scenes "robot;continuous"] [--mixed] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from labels import DEFAULT, LEAVE_OUT, dataset, left_out_share, ra, unknown_share
from scratch import scratch

from tactiled.config import Config
from tactiled.files.recording import Recording
from tactiled.learn.dataset import load_recordings
from tactiled.learn.model import Model
from tactiled.learn.score import score
from tactiled.learn.train import train
from tactiled.run.replay import replay_recording
from tactiled.sim.simulate import write_dataset

UNITS = (1, 2, 3, 4)


def with_and_without(model: Model) -> Iterator[tuple[str, Model]]:
    """The model as trained ("on"), then with no ratio threshold ("off"); restored after."""
    threshold = model.novelty_threshold
    yield "on", model
    model.novelty_threshold = math.inf
    yield "off", model
    model.novelty_threshold = threshold


def accuracy(recs: list[tuple[str, Recording]], config: Config, model: Model) -> dict[str, float]:
    """Accuracy (unknowns wrong), top class and the share of slides called unknown, over every true slide."""
    sc = score(recs, [replay_recording(rec, config, model) for _, rec in recs], model.classes)
    return {"accuracy": sc["accuracy"], "top": sc["top_accuracy"], "unknown": sc["unknown"] / max(1, sc["n"])}


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=DEFAULT, help="scene specs separated by ';'")
    ap.add_argument("--mixed", action="store_true", help="8 grades spread over the range and 7 gratings per scene (bench/labels.py --mixed)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    config = Config()
    root = scratch(args.out, "tactiled-ratio-")
    rows: dict[str, Any] = {}
    print("| scene | ratio threshold | ratio test | same unit | unit 1 | unit 2 | unit 3 | unit 4 | gratings unknown "
          "| left out: unknown of theirs / of known, same unit; unit 1; unit 2 |")
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for spec in args.scenes.split(";"):
        d = root / spec.replace(",", "+")
        tr = dataset(d / "train", spec, 100, 3, 3, args.mixed)
        tests = {"same": load_recordings(dataset(d / "same", spec, 200, 2, 3, args.mixed))}
        for u in UNITS:
            tests[f"unit {u}"] = load_recordings(dataset(d / f"other{u}", spec, 200 + 100 * u, 2, 3, args.mixed, unit=u, specimen=u))
        model = train(tr, config, progress=lambda m: None, novelty="combined").model
        surfaces = sorted({str(s) for _, r in tests["same"] for _, _, s in r.slides()}, key=ra)
        gone = {surfaces[i] for i in LEAVE_OUT}
        keep = [p for p in tr if not any(f"_{g}_" in p.name for g in gone)]
        twelve = train(keep, config, progress=lambda m: None, novelty="combined").model
        far = None if args.mixed or "grating" in spec else load_recordings(
            write_dataset(d / "gratings", scene=f"{spec},grating", seed=400, files_per_surface=1, slides_per_file=3))
        row: dict[str, Any] = {"ratio_threshold": model.novelty_threshold}
        for mode, m in with_and_without(model):
            row[mode] = {k: accuracy(v, config, m) for k, v in tests.items()}
            if far is not None:
                row[mode]["gratings"] = unknown_share(far, config, m)
        for mode, m in with_and_without(twelve):
            row[mode]["left_out"] = {k: left_out_share(tests[k], config, m, gone) for k in ("same", "unit 1", "unit 2")}
        rows[spec] = row
        for mode in ("on", "off"):
            r = row[mode]
            cells = [f"{100 * r[k]['accuracy']:.1f} ({100 * r[k]['unknown']:.1f})" for k in tests]
            grat = f"{r['gratings'][0]} of {r['gratings'][1]}" if "gratings" in r else "-"
            lo = "; ".join(f"{100 * v['unseen']:.0f} / {100 * v['known']:.0f}" for v in r["left_out"].values())
            print(f"| {spec} | {row['ratio_threshold']:.3g} | {mode} | {' | '.join(cells)} | {grat} | {lo} |", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
